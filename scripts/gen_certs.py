"""Generate a test/deployment PKI with the ``openssl`` command line: a CA, a server certificate
for the Zenoh router (or peer) and one client certificate per name (the name is the
certificate's common name, which Zenoh's access control can match with ``cert_common_names``).

    python scripts/gen_certs.py OUT_DIR [--server-name localhost] [--client drone1 ...]

Writes ``ca.pem``, ``ca.key``, ``server.pem``, ``server.key`` and ``<client>.pem`` /
``<client>.key`` (PEM; keys unencrypted, mode 0600). Keys are EC P-256; certificates are valid
for ``--days`` days. The server certificate names ``--server-name`` and 127.0.0.1 / ::1.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path


class CertError(RuntimeError):
    """openssl is missing or failed."""


def _openssl(*args: str, cwd: Path) -> None:
    exe = shutil.which("openssl")
    if exe is None:
        raise CertError("the `openssl` command was not found on PATH; install OpenSSL "
                        "(apt-get install openssl) to generate certificates")
    proc = subprocess.run([exe, *args], cwd=cwd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise CertError(f"openssl {' '.join(args[:2])} failed: {proc.stderr.strip()}")


def _key(out: Path, name: str) -> None:
    _openssl("genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256",
             "-out", f"{name}.key", cwd=out)
    os.chmod(out / f"{name}.key", 0o600)


def _signed(out: Path, name: str, common_name: str, extensions: str, days: int) -> None:
    _key(out, name)
    _openssl("req", "-new", "-key", f"{name}.key", "-subj", f"/CN={common_name}",
             "-out", f"{name}.csr", cwd=out)
    (out / f"{name}.ext").write_text(extensions)
    _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
             "-CAcreateserial", "-days", str(days), "-sha256", "-extfile", f"{name}.ext",
             "-out", f"{name}.pem", cwd=out)
    (out / f"{name}.csr").unlink()
    (out / f"{name}.ext").unlink()


def generate(out_dir: str | Path, *, server_name: str = "localhost",
             clients: Sequence[str] = ("ground", "drone1", "drone2"), days: int = 365
             ) -> dict[str, Path]:
    """Create the CA, ``server`` and ``clients`` certificates in ``out_dir``; name -> the
    certificate's path (``ca``, ``server``, each client). Existing files are overwritten."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    _key(out, "ca")
    _openssl("req", "-x509", "-new", "-key", "ca.key", "-sha256", "-days", str(days),
             "-subj", "/CN=reloc-test-ca", "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign", "-out", "ca.pem", cwd=out)
    _signed(out, "server", server_name,
            "basicConstraints=CA:FALSE\nkeyUsage=digitalSignature\n"
            "extendedKeyUsage=serverAuth,clientAuth\n"
            f"subjectAltName=DNS:{server_name},IP:127.0.0.1,IP:::1\n", days)
    paths = {"ca": out / "ca.pem", "server": out / "server.pem"}
    for name in clients:
        if name in paths or not name.replace("-", "").replace("_", "").isalnum():
            raise CertError(f"client name {name!r}: expected letters, digits, '-' or '_', "
                            "not 'ca' or 'server'")
        _signed(out, name, name, "basicConstraints=CA:FALSE\nkeyUsage=digitalSignature\n"
                "extendedKeyUsage=clientAuth\n" f"subjectAltName=DNS:{name}\n", days)
        paths[name] = out / f"{name}.pem"
    (out / "ca.srl").unlink(missing_ok=True)
    return paths


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out_dir")
    parser.add_argument("--server-name", default="localhost")
    parser.add_argument("--client", action="append", dest="clients", metavar="NAME",
                        help="client certificate common name (repeatable; default: ground, "
                        "drone1, drone2)")
    parser.add_argument("--days", type=int, default=365)
    args = parser.parse_args(argv)
    try:
        paths = generate(args.out_dir, server_name=args.server_name,
                         clients=args.clients or ("ground", "drone1", "drone2"), days=args.days)
    except CertError as exc:
        print(f"gen_certs: error: {exc}", file=sys.stderr)
        return 1
    for name, path in paths.items():
        print(f"{name}: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
