"""Run keys on the command line (docs/hil.md, "Keys and authentication"; the primitives are
bridge/protocol/auth.py): `ambhil key FILE`, the ``--key-file FILE`` / ``--insecure`` flags of
every process command, the safe default that keeps an unauthenticated process on this host,
the per-run key of `ambhil run`, and the ``auth`` line of the summaries.

A secret never appears on a command line or in the environment: processes are handed the
*path* of a key file (``--key-file PATH``; a controller command of the user's gets it in
``$AMBHIL_KEY_FILE``), and the file is mode 0600 in a 0700 folder.

zenoh (bridge/process/transport.py, :func:`is_loopback`) is imported inside the functions:
`ambhil --help` stays quick.
"""
from __future__ import annotations

import os
import shutil
import sys
import tempfile

from ambhil.bridge.cli.convention import CliError, emit
from ambhil.bridge.protocol import auth

ENV = "AMBHIL_KEY_FILE"     # the key file's path for a controller command of the user's
NOT_LOOPBACK = ("{flag} {ep} is not loopback: give --key-file FILE (ambhil key FILE) or --secure DIR, "
                "or --insecure to run unauthenticated")


# --------------------------------------------------------------------------- flags
def add_key_flags(p, run: bool = False) -> None:
    """``--key-file FILE`` and ``--insecure`` of a process command (``run``: of `ambhil run`,
    which makes a key of its own when given none)."""
    if run:
        key_help = ("the run's secret from this key file (`ambhil key FILE`), passed to every process as "
                    "--key-file FILE (to a --controller command in $AMBHIL_KEY_FILE) (default: a fresh "
                    "secret for this run, in a 0600 file in the run's private folder, deleted when the run ends)")
        insecure_help = ("run without a key: every message unauthenticated (anyone who reaches the run's "
                         "links can drive it); the summary says so")
    else:
        key_help = (f"authenticate the run with the secret in this key file (`ambhil key FILE`; mode 0600); "
                    f"every process of the run needs the same one (default: ${ENV} if set, else none: "
                    f"unauthenticated, allowed on loopback only)")
        insecure_help = ("allow running without a key on an endpoint that is not loopback (every message "
                         "unauthenticated; the summary says so)")
    p.add_argument("--key-file", metavar="FILE", help=key_help)
    p.add_argument("--insecure", action="store_true", help=insecure_help)


def key_path(args, env: bool = True) -> str | None:
    """The key file of a process command: ``--key-file``, else ``$AMBHIL_KEY_FILE`` (``env``;
    not with ``--insecure``: the flag given wins over the environment); None for none."""
    path = getattr(args, "key_file", None)
    if path:
        if getattr(args, "insecure", False):
            raise CliError("--key-file and --insecure: give one (a key, or explicitly none)")
        return path
    if env and not getattr(args, "insecure", False):
        return os.environ.get(ENV) or None
    return None


def load_secret(path: str | None) -> bytes | None:
    """The secret in key file ``path`` (None for none); a file that cannot be used is the
    one-line user error of :func:`ambhil.bridge.protocol.auth.read_key_file` (exit 2)."""
    if not path:
        return None
    try:
        return auth.read_key_file(path)
    except auth.AuthError as e:
        raise CliError(str(e)) from None


def process_secret(args) -> tuple[bytes | None, str | None]:
    """(secret, key file) of `ambhil plant|controller|record` and ``replay --to-controller``."""
    path = key_path(args)
    return load_secret(path), path


# --------------------------------------------------------------------------- the safe default
def _as_list(x) -> list[str]:
    return [] if not x else [x] if isinstance(x, str) else list(x)


def not_loopback(listen=None, connect=None) -> str | None:
    """The first endpoint that leaves this host, as ``--listen EP`` / ``--connect EP`` (None if
    every one is loopback or a Unix socket).  A connect endpoint counts too: a session that
    connects across the network also listens there (bridge/process/transport.py,
    ``ephemeral_endpoints``) and its traffic crosses it."""
    from ambhil.bridge.process.transport import is_loopback     # zenoh: see the docstring
    for flag, eps in (("--listen", listen), ("--connect", connect)):
        for ep in _as_list(eps):
            if not is_loopback(ep):
                return f"{flag} {ep}"
    return None


def check_endpoints(listen=None, connect=None, *, secret: bytes | None, secure: str | None,
                    insecure: bool) -> None:
    """Refuse (one line, exit 2) to run unauthenticated beyond this host: an endpoint that is not
    loopback needs a key, ``--secure`` (TLS: only holders of the run's certificates get a link)
    or an explicit ``--insecure``.  Called before any session is opened."""
    if secret is not None or secure or insecure:
        return
    bad = not_loopback(listen, connect)
    if bad:
        flag, ep = bad.split(" ", 1)
        raise CliError(NOT_LOOPBACK.format(flag=flag, ep=ep))


def auth_mode(secret: bytes | None, insecure: bool) -> str:
    """RunAuth's mode (docs/protocol.md): key / insecure / none."""
    return "key" if secret is not None else ("insecure" if insecure else "none")


def auth_text(mode: str, key_file: str | None = None, per_run: bool = False,
              secure: str | None = None) -> str:
    """The ``auth`` line of a summary."""
    if mode == "key":
        return "key (per-run secret)" if per_run else f"key {key_file}"
    if mode == "insecure":
        return "insecure (unauthenticated: --insecure)"
    if secure:
        return "none (no run key; TLS and access control of --secure only)"
    return "none (loopback, unauthenticated)"


def auth_line(role: str, s: dict, key_file: str | None, secure: str | None) -> str:
    """``<role>: auth ...`` of a single process's human summary, with the traffic it rejected
    (by reason) and the strangers it saw."""
    mode = s.get("auth")
    mode = mode.get("mode") if isinstance(mode, dict) else mode
    text = auth_text(mode or ("key" if key_file else "none"), key_file, secure=secure)
    rejected = {k: v for k, v in (s.get("rejected") or {}).items() if v}
    return (f"{role}: auth {text}"
            + (f"; REJECTED {', '.join(f'{k} {v}' for k, v in sorted(rejected.items()))}" if rejected else "")
            + "".join(f"; stranger {x} failed the pairing proof" for x in s.get("strangers") or []))


# --------------------------------------------------------------------------- ambhil key
def cmd_key(args) -> int:
    """`ambhil key FILE [--force]`: a new secret, 64 hex digits, mode 0600."""
    try:
        auth.write_key_file(args.file, force=args.force)
    except auth.AuthError as e:
        raise CliError(str(e)) from None
    path = os.path.abspath(args.file)
    emit(args, {"command": "key", "file": path, "mode": "0600"}, [
        f"wrote a new run secret to {path} (mode 0600: keep it that way)",
        f"use it on every process of the run: --key-file {path}  (ambhil run, plant, controller, record, "
        f"replay --to-controller, test-controller)",
        f"another host: copy it with `scp -p {path} HOST:` (check `chmod 600` there); anyone who holds it "
        f"can drive the run"])
    return 0


# --------------------------------------------------------------------------- ambhil run's key
def _private_folder() -> tuple[str, bool]:
    """(folder, made here): the run's private folder of Unix sockets (0700, ours;
    bridge/process/transport.py ``socket_dir``), else a fresh 0700 temporary folder."""
    try:
        from ambhil.bridge.process import transport as tr     # zenoh: see the docstring
        d = tr.socket_dir()
        st = os.stat(d)
        if st.st_uid == os.getuid() and not st.st_mode & 0o077:
            tr.remove_stale_sockets(d)      # key files of runs killed before they could delete them
            return d, False
    except OSError:
        pass
    return tempfile.mkdtemp(prefix="ambhil-key-"), True     # mkdtemp makes it 0700


class RunKey:
    """The key of one `ambhil run`: ``--key-file FILE`` (read, checked), ``--insecure`` (none),
    or a fresh secret written 0600 to ``<private folder>/<run>-<pid>.key``, removed by
    :meth:`close` (the run ends, also on failure; after a SIGKILL the next run removes it).
    ``argv`` is what each child of ours gets, ``env`` what a command of the user's gets."""

    def __init__(self, args, run_id: str):
        self.insecure = bool(getattr(args, "insecure", False))
        given = key_path(args, env=False)
        self.per_run = not given and not self.insecure
        self._made: str | None = None
        self._folder: str | None = None
        if given:
            self.secret = load_secret(given)
            self.path: str | None = os.path.abspath(given)
        elif self.insecure:
            self.secret, self.path = None, None
        else:
            folder, made = _private_folder()
            self._folder = folder if made else None
            self.path = os.path.join(folder, f"{run_id[:40]}-{os.getpid()}.key")
            try:
                self.secret = auth.write_key_file(self.path, force=True)
            except auth.AuthError as e:
                self.close()
                raise CliError(f"cannot write the run's key: {e}", 1) from None
            self._made = self.path
        self.mode = auth_mode(self.secret, self.insecure)

    @property
    def argv(self) -> list[str]:
        """The flags of a child of ours: ``--key-file PATH`` (never the secret) or ``--insecure``."""
        return ["--key-file", self.path] if self.path else ["--insecure"] if self.insecure else []

    @property
    def env(self) -> dict:
        """``AMBHIL_KEY_FILE`` for every child (None: removed from what they inherit)."""
        return {ENV: self.path}

    def text(self, secure: str | None = None) -> str:
        return auth_text(self.mode, self.path, self.per_run, secure)

    def describe(self, secure: str | None = None) -> dict:
        """The summary's ``auth``: mode, its line, the key file given (None for a per-run one)."""
        return {"mode": self.mode, "text": self.text(secure), "per_run": self.per_run,
                "key_file": None if self.per_run else self.path}

    def close(self) -> None:
        """Delete the per-run key file (and a temporary folder made for it); idempotent."""
        if self._made:
            try:
                os.unlink(self._made)
            except FileNotFoundError:
                pass
            except OSError as e:
                print(f"ambhil run: warning: could not delete the run's key file {self._made}: "
                      f"{e.strerror}", file=sys.stderr)
            self._made = None
        if self._folder:
            shutil.rmtree(self._folder, ignore_errors=True)
            self._folder = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
