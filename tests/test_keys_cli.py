"""Run keys on the command line (bridge/cli/keyfile.py, docs/hil.md "Keys and authentication"):
`ambhil key` writes a 0600 key file and never replaces one by accident; a key file others can
read, or that holds no secret, is refused in one line; nothing listens or connects beyond this
host without a key, --secure or --insecure, and that is refused before any session is opened;
`ambhil run` hands its children the key file's path (never the secret) and deletes the file
when the run ends; the summaries name the mode, the rejected traffic and the strangers; each
role's ACL lets it put only its own event key, the recorder nothing."""
from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from ambhil.bridge.cli import keyfile
from ambhil.bridge.cli import main as cli
from ambhil.bridge.protocol import auth

ROOT = Path(__file__).resolve().parents[1]
SCENE = str(ROOT / "scenes" / "paper_2amb.toml")


def ambhil(*args, timeout=300, env=None):
    return subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=ROOT)


def _one_error_line(r, command: str) -> str:
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert len(lines) == 1 and lines[0].startswith(f"ambhil {command}: error: "), r.stderr
    assert "Traceback" not in r.stderr
    return lines[0]


# --------------------------------------------------------------------------- key files
def test_key_file_is_0600_and_never_replaced_without_force(tmp_path, capsys):
    k = tmp_path / "run.key"
    assert cli.main(["key", str(k)]) == 0
    assert "--key-file" in capsys.readouterr().out
    assert stat.S_IMODE(k.stat().st_mode) == 0o600
    secret = auth.read_key_file(str(k))
    assert len(secret) == 32 and k.read_text().strip() == secret.hex()
    assert cli.main(["key", str(k)]) == 2
    err = capsys.readouterr().err
    assert "exists" in err and "--force" in err and len(err.strip().splitlines()) == 1, err
    assert auth.read_key_file(str(k)) == secret                 # untouched
    assert cli.main(["key", str(k), "--force"]) == 0
    assert auth.read_key_file(str(k)) != secret and stat.S_IMODE(k.stat().st_mode) == 0o600


def test_a_key_file_others_can_read_is_refused_in_one_line(tmp_path):
    k = tmp_path / "open.key"
    auth.write_key_file(str(k))
    os.chmod(k, 0o644)
    r = ambhil("controller", SCENE, "--run-id", "k1", "--connect", "tcp/127.0.0.1:9", "--key-file", str(k))
    line = _one_error_line(r, "controller")
    assert str(k) in line and f"chmod 600 {k}" in line and "0644" in line, line


@pytest.mark.parametrize("text", ["not a key\n", "ab" * 31 + "\n", "00" * 32 + "\n", ""])
def test_a_key_file_without_a_secret_is_refused(tmp_path, text):
    k = tmp_path / "bad.key"
    k.write_text(text)
    os.chmod(k, 0o600)
    with pytest.raises(auth.AuthError) as e:
        auth.read_key_file(str(k))
    assert str(k) in str(e.value)
    r = ambhil("plant", SCENE, "--run-id", "k2", "--listen", "tcp/127.0.0.1:0", "--key-file", str(k))
    assert str(k) in _one_error_line(r, "plant")


def test_a_missing_key_file_names_the_command_that_makes_one(tmp_path):
    k = tmp_path / "none.key"
    r = ambhil("record", "--run-id", "k3", "--key-file", str(k), "--out", str(tmp_path))
    line = _one_error_line(r, "record")
    assert f"ambhil key {k}" in line, line


# --------------------------------------------------------------------------- the safe default
def test_is_loopback():
    from ambhil.bridge.process.transport import is_loopback
    for ep in ("tcp/127.0.0.1:7447", "tcp/127.3.4.5:1", "tcp/[::1]:7447", "tcp/localhost:7447",
               "tls/127.0.0.1:7447", "udp/127.0.0.1:7447", "unixsock-stream//run/user/1/ambhil/x.sock",
               "tcp/127.0.0.1:7447?iface=lo"):
        assert is_loopback(ep), ep
    for ep in ("tcp/0.0.0.0:7447", "tcp/[::]:7447", "tcp/10.0.0.1:7447", "tls/192.168.1.2:7447",
               "tcp/example.org:7447", "tcp/[fe80::1]:7447", "tcp/127.0.0.1", "garbage", ""):
        assert not is_loopback(ep), ep


def test_check_endpoints_refuses_to_leave_the_host_without_a_key():
    from ambhil.bridge.cli.convention import CliError
    for listen, connect in (("tcp/0.0.0.0:7447", None), ("tcp/[::]:7447", None),
                            (None, ["tcp/127.0.0.1:7448", "tcp/10.0.0.1:7447"])):
        with pytest.raises(CliError) as e:
            keyfile.check_endpoints(listen, connect, secret=None, secure=None, insecure=False)
        msg = str(e.value)
        assert "is not loopback: give --key-file FILE (ambhil key FILE) or --secure DIR, or --insecure " \
               "to run unauthenticated" in msg and e.value.code == 2, msg
    assert "--listen tcp/10.0.0.1:7447 is not loopback" in str(pytest.raises(
        CliError, keyfile.check_endpoints, "tcp/10.0.0.1:7447", None, secret=None, secure=None,
        insecure=False).value)
    for ok in ({"secret": b"k" * 32, "secure": None, "insecure": False},
               {"secret": None, "secure": "certs/", "insecure": False},
               {"secret": None, "secure": None, "insecure": True}):
        keyfile.check_endpoints("tcp/0.0.0.0:7447", ["tcp/10.0.0.1:7448"], **ok)
    keyfile.check_endpoints("tcp/127.0.0.1:7447", ["unixsock-stream//tmp/x.sock"], secret=None,
                            secure=None, insecure=False)


def test_plant_listening_on_every_interface_without_a_key_exits_2():
    r = ambhil("plant", SCENE, "--run-id", "k4", "--listen", "tcp/0.0.0.0:0")
    line = _one_error_line(r, "plant")
    assert line == ("ambhil plant: error: --listen tcp/0.0.0.0:0 is not loopback: give --key-file FILE "
                    "(ambhil key FILE) or --secure DIR, or --insecure to run unauthenticated"), line
    assert "plant:" not in r.stderr.replace("ambhil plant:", "")     # no start-up step: no session


class _Reached(Exception):
    pass


def test_the_refusal_comes_before_any_session_and_insecure_lifts_it(monkeypatch):
    """In process, with every way to a zenoh session made to fail loudly: the refusal is a
    user error (the session was never tried); with --insecure the command goes on to open it."""
    import zenoh
    from ambhil.bridge.cli.convention import HARD_EXIT
    from ambhil.bridge.process import startup, transport

    def _no(*a, **k):
        raise _Reached("a session was opened")
    monkeypatch.setattr(zenoh, "open", _no)
    monkeypatch.setattr(transport, "open_session", _no)
    monkeypatch.setattr(startup.Presence, "open", classmethod(lambda cls, *a, **k: _no()))
    monkeypatch.delenv(keyfile.ENV, raising=False)
    monkeypatch.setenv("AMBHIL_DEBUG", "1")      # main re-raises an unforeseen exception (ours)
    try:
        base = ["plant", SCENE, "--run-id", "k5", "--listen", "tcp/0.0.0.0:0"]
        assert cli.main(base) == 2
        with pytest.raises(_Reached):
            cli.main(base + ["--insecure"])
    finally:
        HARD_EXIT[0] = False


def test_key_file_and_insecure_together_are_refused(tmp_path):
    k = tmp_path / "r.key"
    auth.write_key_file(str(k))
    r = ambhil("controller", SCENE, "--run-id", "k6", "--connect", "tcp/127.0.0.1:9", "--key-file", str(k),
               "--insecure")
    assert "give one" in _one_error_line(r, "controller")
    r = ambhil("run", SCENE, "--key-file", str(k), "--insecure", "--out", str(tmp_path))
    assert "give one" in _one_error_line(r, "run")
    os.chmod(k, 0o640)                        # refused before the model is built or anything starts
    r = ambhil("run", SCENE, "--key-file", str(k), "--out", str(tmp_path))
    assert f"chmod 600 {k}" in _one_error_line(r, "run") and not list(tmp_path.glob("*.mcap"))


# --------------------------------------------------------------------------- ambhil run's key
def _run_args(*extra):
    args = cli.build_parser().parse_args(["run", SCENE, "--placement", "none", *extra])
    from ambhil.loop.scene import load_scene
    return args, load_scene(SCENE)


def test_run_children_get_the_key_file_path_never_the_secret(tmp_path, monkeypatch):
    from ambhil.bridge.cli.run import child_argvs
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    args, scene = _run_args("--controller", "mine --key {key_file} --connect {connect}")
    key = keyfile.RunKey(args, "r1")
    try:
        assert key.per_run and key.mode == "key" and key.text() == "key (per-run secret)"
        path = Path(key.path)
        assert path.parent == tmp_path / "ambhil" and path.name == f"r1-{os.getpid()}.key"
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
        assert auth.read_key_file(str(path)) == key.secret
        argvs = child_argvs(args, scene, 10, 0.0, "r1", tmp_path, "tcp/127.0.0.1:1", "tcp/127.0.0.1:2", True, key)
        hexed = key.secret.hex()
        for name, (argv, external) in argvs.items():
            text = " ".join(argv)
            assert hexed not in text.lower() and key.secret.hex().upper() not in text, name
            assert str(path) in argv, (name, argv)
            if not external:
                assert argv[argv.index("--key-file") + 1] == str(path), name
        assert argvs["controller"][1] and argvs["controller"][0][:3] == ["mine", "--key", str(path)]
        assert key.env == {keyfile.ENV: str(path)} and hexed not in str(key.env)
        assert key.describe()["key_file"] is None          # a per-run key's path is not worth keeping
    finally:
        key.close()
    assert not path.exists()
    key.close()                                              # idempotent


def test_run_with_a_key_file_uses_it_and_keeps_it(tmp_path):
    from ambhil.bridge.cli.run import child_argvs
    k = tmp_path / "mine.key"
    secret = auth.write_key_file(str(k))
    args, scene = _run_args("--key-file", str(k))
    with keyfile.RunKey(args, "r2") as key:
        assert key.secret == secret and not key.per_run and key.text() == f"key {k}"
        argvs = child_argvs(args, scene, 10, 0.0, "r2", tmp_path, "tcp/127.0.0.1:1", "tcp/127.0.0.1:2", False, key)
        assert argvs["recorder"] is None
        for argv, _ in filter(None, argvs.values()):
            assert argv[argv.index("--key-file") + 1] == str(k) and secret.hex() not in " ".join(argv)
    assert k.exists()                                         # the user's file is never deleted


def test_run_insecure_passes_insecure_and_no_key(tmp_path, monkeypatch):
    from ambhil.bridge.cli.run import child_argvs
    monkeypatch.setenv(keyfile.ENV, "/somewhere/else.key")     # the user's shell: not this run's key
    args, scene = _run_args("--insecure")
    with keyfile.RunKey(args, "r3") as key:
        assert key.mode == "insecure" and key.path is None and "unauthenticated: --insecure" in key.text()
        argvs = child_argvs(args, scene, 10, 0.0, "r3", tmp_path, "tcp/127.0.0.1:1", "tcp/127.0.0.1:2", True, key)
        for argv, _ in argvs.values():
            assert "--insecure" in argv and "--key-file" not in argv
        assert key.env == {keyfile.ENV: None}
    from ambhil.bridge.cli.children import child_env
    assert keyfile.ENV not in child_env(key.env)


def test_the_run_key_file_is_gone_after_the_run(tmp_path):
    """A real `ambhil run` whose controller command copies what it was given and fails: the key
    reached it as a path in $AMBHIL_KEY_FILE (0600), the secret is in no environment variable,
    and the file is deleted when the run ends (here: failed)."""
    seen = tmp_path / "seen"
    cmd = (f"sh -c 'cp \"$AMBHIL_KEY_FILE\" {seen}.key; stat -c %a \"$AMBHIL_KEY_FILE\" > {seen}.mode; "
           f"echo \"$AMBHIL_KEY_FILE\" > {seen}.path; env > {seen}.env; echo {{key_file}} > {seen}.arg; exit 3'")
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", XDG_RUNTIME_DIR=str(tmp_path))
    env.pop(keyfile.ENV, None)
    r = ambhil("run", SCENE, "--run-id", "keygone", "--duration", "0.002", "--no-record", "--placement", "none",
               "--start-timeout", "3", "--out", str(tmp_path / "out"), "--controller", cmd, "--json",
               env=env, timeout=600)
    assert r.returncode != 0, r.stderr
    path = Path((tmp_path / "seen.path").read_text().strip())
    assert (tmp_path / "seen.arg").read_text().strip() == str(path)
    assert path.parent == tmp_path / "ambhil" and path.name.startswith("keygone-")
    assert (tmp_path / "seen.mode").read_text().strip() == "600"
    secret = (tmp_path / "seen.key").read_text().strip()
    assert len(secret) == 64 and secret not in (tmp_path / "seen.env").read_text()
    assert not path.exists(), "the run's key file outlived the run"
    assert not list((tmp_path / "ambhil").glob("*.key"))


def test_strict_fails_a_run_that_met_a_stranger(tmp_path):
    """A controller without the run's key announces itself beside the real one: the run pairs
    with the real one and completes, but names the stranger; --strict fails it: exit 1, files
    .failed, the recording's run_end status failed with that reason (and its auth mode kept)."""
    import json
    import shlex
    from ambhil.bridge.recording.run_end import run_end_of
    py = shlex.quote(sys.executable)
    ctl = f"{py} -m ambhil.bridge.cli controller {{scene}} --run-id {{run_id}} --connect {{connect}} --json"
    # the stranger first, and the real controller only once the stranger is ready (announced):
    # started side by side, on a busy machine the stranger came up after the 200-step run ended
    log = tmp_path / "stranger.log"
    wait = f"until grep -q 'waiting for plant' {shlex.quote(str(log))} 2>/dev/null; do sleep 0.05; done"
    cmd = f"sh -c {shlex.quote(f'env -u {keyfile.ENV} {ctl} >/dev/null 2>{shlex.quote(str(log))} & {wait}; exec {ctl}')}"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", XDG_RUNTIME_DIR=str(tmp_path))
    r = ambhil("run", SCENE, "--run-id", "stranger", "--duration", "0.02", "--placement", "none", "--strict",
               "--out", str(tmp_path), "--controller", cmd, "--json", env=env, timeout=900)
    s = json.loads(r.stdout.strip().splitlines()[-1])
    assert r.returncode == 1, r.stderr[-2000:]
    assert s["auth"]["mode"] == "key" and s["auth"]["per_run"] and len(s["strangers"]) == 1, s
    assert s["plant"]["steps"] == s["plant"]["n_steps"] == 200, s["plant"]
    line = f"stranger {s['strangers'][0]} failed the pairing proof"
    assert any(x.startswith("--strict: ") and line in x for x in s["failed"]), s["failed"]
    end = run_end_of(str(tmp_path / "stranger.failed.mcap"))
    assert end["status"] == "failed" and line in end["fault"] and end["auth"] == "key", end
    assert not list((tmp_path / "ambhil").glob("*.key"))


# --------------------------------------------------------------------------- summaries
def test_summaries_name_the_mode_the_auth_rejections_and_the_strangers():
    from ambhil.bridge.cli.run_verdict import foreign_report
    assert keyfile.auth_text("none") == "none (loopback, unauthenticated)"
    assert keyfile.auth_text("key", "/k/run.key") == "key /k/run.key"
    assert keyfile.auth_text("key", "/x", per_run=True) == "key (per-run secret)"
    assert keyfile.auth_text("insecure") == "insecure (unauthenticated: --insecure)"
    sid = "ab" * 16
    sp = {"rejected_total": 3, "rejected": {"auth": 2, "sequence": 1}, "strangers": [sid], "foreign_copied": 2}
    sc = {"rejected_total": 0, "rejected": {}, "strangers": [sid]}
    line = foreign_report(sp, sc, {"rejected": {"auth": 4}})
    assert "plant rejected 3 messages (auth 2, sequence 1)" in line
    assert "recorder rejected 4 messages (auth 4)" in line
    assert line.count(f"stranger {sid} failed the pairing proof") == 1
    assert "another process published into this run" in line
    assert foreign_report({"rejected_total": 0, "rejected": {}}, None) is None
    assert foreign_report({"rejected_total": 0, "rejected": {}, "strangers": [sid]}, None) == \
        f"stranger {sid} failed the pairing proof"            # a stranger alone fails --strict
    al = keyfile.auth_line("plant", {"auth": "key", "rejected": {"auth": 2}, "strangers": [sid]}, "/k", None)
    assert al == f"plant: auth key /k; REJECTED auth 2; stranger {sid} failed the pairing proof"


def test_acl_lets_each_role_put_only_its_own_event_key():
    from ambhil.bridge.process import security
    acl = security.acl("r9")
    rules = {r["id"]: r for r in acl["rules"]}
    policies = {p["subjects"][0]: p["rules"] for p in acl["policies"]}
    assert "recorder_put" not in rules and "recorder_put" not in policies["recorder"]
    plant = rules["plant_put"]["key_exprs"]
    ctl = rules["controller_put"]["key_exprs"]
    assert "ambhil/r9/events/plant" in plant and not any("events/controller" in k for k in plant)
    assert "ambhil/r9/events/controller" in ctl and not any("events/plant" in k for k in ctl)
    assert "ambhil/r9/events" not in plant + ctl and "ambhil/r9/controller/currents" not in plant
    decl = rules["run_decl"]
    assert {"query", "reply"} <= set(decl["messages"])
    assert decl["key_exprs"] == ["ambhil/r9/**"]             # the pairing challenges on pair/**
    # tokens and queryables: each role only its own (a recorder's certificate cannot announce a
    # controller, nor answer its challenges)
    assert "liveliness_token" not in decl["messages"] and "declare_queryable" not in decl["messages"]
    for role in security.ROLES:
        own = rules[f"{role}_own"]
        assert own["flows"] == ["ingress"] and f"{role}_own" in policies[role]
        assert set(own["messages"]) == {"liveliness_token", "declare_queryable"}
        assert {f"ambhil/r9/alive/{role}", f"ambhil/r9/peer/{role}/*",
                f"ambhil/r9/pair/{role}/*"} <= set(own["key_exprs"])
        others = [r for r in security.ROLES if r != role]
        assert not any(f"/{o}" in k for k in own["key_exprs"] for o in others), own
