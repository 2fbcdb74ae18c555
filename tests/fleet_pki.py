"""A fleet's certificates made with `openssl`, the commands docs/fleet.md gives."""

from __future__ import annotations

import subprocess
from pathlib import Path


def _run(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


def make_ca(folder: Path, name: str = "ca") -> Path:
    """A fleet CA: <name>.key, <name>.pem (EC P-256, self-signed)."""
    folder.mkdir(parents=True, exist_ok=True)
    _run("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
         "-keyout", f"{name}.key", "-out", f"{name}.pem", "-days", "3650",
         "-subj", f"/CN=nislam fleet CA {name}", cwd=folder)
    return folder / f"{name}.pem"


def make_cert(folder: Path, cn: str, ca: str = "ca") -> tuple[str, str]:
    """<cn>.pem / <cn>.key signed by the CA <ca>: common name = the vehicle id
    (or ground / router), subjectAltName for 127.0.0.1 and localhost."""
    _run("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
         "-keyout", f"{cn}.key", "-out", f"{cn}.csr", "-subj", f"/CN={cn}", cwd=folder)
    (folder / f"{cn}.ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    _run("x509", "-req", "-in", f"{cn}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key",
         "-CAcreateserial", "-out", f"{cn}.pem", "-days", "825", "-extfile", f"{cn}.ext",
         cwd=folder)
    return str(folder / f"{cn}.pem"), str(folder / f"{cn}.key")
