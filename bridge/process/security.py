"""Secure runs: mutual TLS between the run's processes and zenoh access control that allows each
role only the run's keys it needs (docs/hil.md, "Secure runs").

``ambhil certs DIR`` makes a CA and one certificate per role (common name = the role), with the
``openssl`` command.  ``--secure DIR`` on ``ambhil plant|controller|record|run`` makes every zenoh
session of that process

- speak TLS only, with mutual authentication against ``DIR/ca.pem`` (a peer without a
  certificate of that CA cannot connect), and
- enforce :func:`acl` on everything it sends and receives: a peer is identified by its
  certificate's common name; each role may publish (``put``) only its own keys of this run
  (plant: sensors, events/plant, meta, timing, record, its foreign copies; controller: currents,
  events/controller, its foreign copies; recorder: nothing),
  declarations, liveliness and queries only within ``ambhil/<run>/**``, and liveliness tokens
  and queryables only of its own role (``starting|alive/<role>``, ``peer/<role>/*``,
  ``pair/<role>/*``, ``status/<role>``: a recorder's certificate cannot announce a controller);
  everything else is denied.  Every session enforces it, so a peer holding the recorder's certificate cannot drive
  the coils, and no certificate of another name reaches the run at all.
- Events per role (protocol 3): the plant puts only on ``events/plant``, the controller only on
  ``events/controller``, the recorder puts nothing at all; the pairing challenges are queries
  and replies on ``pair/**``, allowed within the run like every declaration.  The replay tool
  (``replay --to-controller``) poses as the plant and uses the plant's certificate.

The run key applies on top and independently (bridge/protocol/auth.py: a MAC on every message;
the pairing of bridge/process/pairing.py, a challenge-response under it, which also refuses a
second process of the right role): TLS and the ACL keep peers without a certificate off the
links, the key keeps messages without the run's secret out of the loop.
"""
from __future__ import annotations

import os
import shutil
import subprocess

from ambhil.bridge import protocol as pr

ROLES = ("plant", "controller", "recorder")
# keys (below ambhil/<run>/) each role may put
PUTS = {"plant": ("plant/sensors", "events/plant", "meta", "timing", "record",
                  "foreign/controller/currents"),
        "controller": ("controller/currents", "events/controller", "foreign/plant/sensors"),
        "recorder": ()}
_DECL = ["declare_subscriber", "query", "reply", "liveliness_query",
         "declare_liveliness_subscriber"]
# what announces a process (liveliness tokens) or answers for it (queryables): each role only
# its own (below ambhil/<run>/), so a certificate of one role cannot pose as another's peer
_OWN = ["liveliness_token", "declare_queryable"]


def owns(role: str) -> tuple[str, ...]:
    """The keys (below ``ambhil/<run>/``) of ``role``'s tokens and queryables."""
    return (f"starting/{role}", f"alive/{role}", f"peer/{role}/*", f"pair/{role}/*",
            f"status/{role}")


class SecurityError(ValueError):
    """Certificates missing, unreadable, or cannot be made."""


def acl(run_id: str) -> dict:
    """zenoh ``access_control`` for run ``run_id``: default deny; per role (certificate common
    name) the puts of :data:`PUTS` on ingress; declarations, liveliness and queries within the
    run's keys both ways; our own puts within the run's keys on egress."""
    root = pr.keys(run_id).root
    rules = [{"id": "run_decl", "messages": _DECL, "flows": ["ingress", "egress"],
              "permission": "allow", "key_exprs": [f"{root}/**"]},
             {"id": "run_egress", "messages": ["put", "delete"], "flows": ["egress"],
              "permission": "allow", "key_exprs": [f"{root}/**"]},
             {"id": "run_own_egress", "messages": _OWN, "flows": ["egress"],
              "permission": "allow", "key_exprs": [f"{root}/**"]}]
    policies = []
    for role in ROLES:
        rules.append({"id": f"{role}_own", "messages": _OWN, "flows": ["ingress"],
                      "permission": "allow", "key_exprs": [f"{root}/{k}" for k in owns(role)]})
        own = ["run_decl", "run_egress", "run_own_egress", f"{role}_own"]
        if PUTS[role]:          # a rule needs a key; a role that puts nothing gets no put rule
            rules.append({"id": f"{role}_put", "messages": ["put"], "flows": ["ingress"],
                          "permission": "allow", "key_exprs": [f"{root}/{k}" for k in PUTS[role]]})
            own.append(f"{role}_put")
        policies.append({"id": f"{role}_policy", "rules": own, "subjects": [role]})
    subjects = [{"id": r, "cert_common_names": [r]} for r in ROLES]
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


def files(folder: str, role: str) -> dict:
    """The CA and ``role``'s key and certificate in ``folder``; SecurityError naming what is
    missing."""
    if role not in ROLES:
        raise SecurityError(f"unknown role {role!r}: one of {', '.join(ROLES)}")
    out = {"ca": os.path.join(folder, "ca.pem"), "key": os.path.join(folder, f"{role}.key"),
           "cert": os.path.join(folder, f"{role}.pem")}
    for what, path in out.items():
        if not os.path.isfile(path):
            raise SecurityError(f"--secure {folder}: {what} file {path} missing "
                                f"(make them with `ambhil certs {folder}`)")
    return out


def tls(folder: str, role: str) -> dict:
    """zenoh ``transport/link/tls`` for ``role``: mutual TLS with the folder's CA."""
    f = files(folder, role)
    return {"root_ca_certificate": f["ca"], "enable_mtls": True,
            "listen_private_key": f["key"], "listen_certificate": f["cert"],
            "connect_private_key": f["key"], "connect_certificate": f["cert"]}


def session_extra(folder: str, role: str, run_id: str) -> dict:
    """Config entries (zenoh key path -> value) of a secure session of ``role`` in the run."""
    return {"transport/link/tls": tls(folder, role), "access_control": acl(run_id)}


def configure(folder: str | None, role: str, run_id: str) -> None:
    """Make every session this process opens from now on secure (:mod:`ambhil.bridge.process.transport`)."""
    from ambhil.bridge.process import transport as tr
    tr.SECURE = None if folder is None else session_extra(folder, role, run_id)


def make_certs(folder: str, roles=ROLES, days: int = 825, host: str = "127.0.0.1",
               force: bool = False) -> list[str]:
    """A CA and one certificate per role (CN = role; SAN = ``host`` and localhost; server and
    client use) in ``folder``, with ``openssl``.  Refuses to overwrite unless ``force``.  Returns
    the files written."""
    exe = shutil.which("openssl")
    if exe is None:
        raise SecurityError("`openssl` not found on PATH: install it (Debian: openssl) to make "
                            "certificates, or bring your own (docs/hil.md, Secure runs)")
    os.makedirs(folder, exist_ok=True)
    if not force and os.path.exists(os.path.join(folder, "ca.pem")):
        raise SecurityError(f"{folder}/ca.pem exists: use --force to replace the certificates")

    def sh(*args):
        r = subprocess.run([exe, *args], capture_output=True, text=True, cwd=folder)
        if r.returncode != 0:
            raise SecurityError(f"openssl {args[0]} failed: {r.stderr.strip().splitlines()[-1:]}")
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes"]
    sh("req", "-x509", *ec, "-keyout", "ca.key", "-out", "ca.pem", "-days", str(days),
       "-subj", "/CN=ambhil-ca")
    san = f"IP:{host},DNS:localhost" if host.replace(".", "").isdigit() else f"DNS:{host},DNS:localhost"
    written = ["ca.key", "ca.pem"]
    for r in roles:
        sh("req", *ec, "-keyout", f"{r}.key", "-out", f"{r}.csr", "-subj", f"/CN={r}")
        with open(os.path.join(folder, f"{r}.ext"), "w") as fh:
            fh.write(f"subjectAltName={san}\nextendedKeyUsage=serverAuth,clientAuth\n")
        sh("x509", "-req", "-in", f"{r}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
           "-CAcreateserial", "-out", f"{r}.pem", "-days", str(days), "-extfile", f"{r}.ext")
        for tmp in (f"{r}.csr", f"{r}.ext"):
            os.unlink(os.path.join(folder, tmp))
        written += [f"{r}.key", f"{r}.pem"]
    for f in written:
        if f.endswith(".key"):
            os.chmod(os.path.join(folder, f), 0o600)
    return [os.path.join(folder, f) for f in written]
