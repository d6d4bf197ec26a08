#!/usr/bin/env python3
"""Generate a throwaway certificate authority and TLS certificates for the secure Zenoh profile.

Writes into OUT_DIR (default: ``certs/`` beside this script, which git ignores):

    ca.pem, ca-key.pem            the certificate authority (keep ca-key.pem private)
    server.pem, server-key.pem    the router's certificate, for localhost and 127.0.0.1
                                  plus any --host names or addresses you add
    client-NAME.pem, -key.pem     optional client certificates (CN = NAME) for mutual TLS

Uses the ``cryptography`` package when it is installed, otherwise the ``openssl`` command.
Keys are ECDSA P-256 in PKCS#8 PEM, which Zenoh's TLS stack (rustls) reads.

These certificates are for trying the profile and for tests. For a real deployment use
your organisation's CA, or at least keep the CA key offline and pass the real host names
of the router with --host.

    python deploy/zenoh/secure/make_certs.py deploy/zenoh/secure/certs --host base.local \
        --client robot0 --client gpu --client base --client client
"""

from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

DEFAULT_OUT = Path(__file__).resolve().parent / "certs"
DEFAULT_HOSTS = ("localhost", "127.0.0.1")


def _is_ip(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


def _have_cryptography() -> bool:
    try:
        import cryptography.x509  # noqa: F401
    except ImportError:
        return False
    return True


# --------------------------------------------------------------------------- cryptography


def _write_key(path: Path, key) -> None:
    from cryptography.hazmat.primitives import serialization

    data = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    _write_private(path, data)


def _write_private(path: Path, data: bytes) -> None:
    """Write a private key readable by its owner only (also when replacing a file)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        os.fchmod(f.fileno(), 0o600)
        f.write(data)


def _make_with_cryptography(out: Path, hosts: list[str], clients: list[str], days: int) -> None:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = dt.datetime.now(dt.timezone.utc) - dt.timedelta(minutes=5)
    until = now + dt.timedelta(days=days)

    def name(cn: str) -> x509.Name:
        return x509.Name([
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "TrackGraph test"),
            x509.NameAttribute(NameOID.COMMON_NAME, cn),
        ])  # fmt: skip

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = name("TrackGraph throwaway CA")
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now)
        .not_valid_after(until)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True, content_commitment=False, key_encipherment=False,
                data_encipherment=False, key_agreement=False, key_cert_sign=True, crl_sign=True,
                encipher_only=False, decipher_only=False,
            ),  # fmt: skip
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    _write_key(out / "ca-key.pem", ca_key)
    (out / "ca.pem").write_bytes(ca.public_bytes(serialization.Encoding.PEM))

    def leaf(cn: str, sans: list[str], usage) -> tuple:
        key = ec.generate_private_key(ec.SECP256R1())
        builder = (
            x509.CertificateBuilder()
            .subject_name(name(cn))
            .issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now)
            .not_valid_after(until)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.KeyUsage(
                    digital_signature=True, content_commitment=False, key_encipherment=False,
                    data_encipherment=False, key_agreement=False, key_cert_sign=False, crl_sign=False,
                    encipher_only=False, decipher_only=False,
                ),  # fmt: skip
                critical=True,
            )
            .add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
            .add_extension(
                x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
            )
        )
        if sans:
            alt = [x509.IPAddress(ipaddress.ip_address(h)) if _is_ip(h) else x509.DNSName(h) for h in sans]
            builder = builder.add_extension(x509.SubjectAlternativeName(alt), critical=False)
        return key, builder.sign(ca_key, hashes.SHA256())

    key, cert = leaf(hosts[0], hosts, ExtendedKeyUsageOID.SERVER_AUTH)
    _write_key(out / "server-key.pem", key)
    (out / "server.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    for c in clients:
        key, cert = leaf(c, [], ExtendedKeyUsageOID.CLIENT_AUTH)
        _write_key(out / f"client-{c}-key.pem", key)
        (out / f"client-{c}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))


# --------------------------------------------------------------------------- openssl


def _openssl(*args: str, cwd: Path) -> None:
    proc = subprocess.run(["openssl", *args], cwd=cwd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"openssl {' '.join(args[:2])} failed: {proc.stderr.strip()}")


def _make_with_openssl(out: Path, hosts: list[str], clients: list[str], days: int) -> None:
    if shutil.which("openssl") is None:
        raise RuntimeError("neither the 'cryptography' package nor the 'openssl' command is available")
    with tempfile.TemporaryDirectory(prefix="tg-certs-") as tmp:
        work = Path(tmp)
        (work / "ca.ext").write_text(
            "basicConstraints=critical,CA:TRUE,pathlen:0\n"
            "keyUsage=critical,digitalSignature,keyCertSign,cRLSign\n"
            "subjectKeyIdentifier=hash\n"
        )
        _openssl("genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", "ca-key.pem", cwd=work)
        _openssl(
            "req", "-new", "-x509", "-key", "ca-key.pem", "-sha256", "-days", str(days),
            "-subj", "/O=TrackGraph test/CN=TrackGraph throwaway CA",
            "-extensions", "v3_ca_tg", "-config", str(_req_config(work)), "-out", "ca.pem",
            cwd=work,
        )  # fmt: skip

        def leaf(stem: str, cn: str, sans: list[str], usage: str) -> None:
            ext = [
                "basicConstraints=critical,CA:FALSE",
                "keyUsage=critical,digitalSignature",
                f"extendedKeyUsage={usage}",
                "authorityKeyIdentifier=keyid",
            ]
            if sans:
                ext.append("subjectAltName=" + ",".join(("IP:" if _is_ip(h) else "DNS:") + h for h in sans))
            (work / f"{stem}.ext").write_text("\n".join(ext) + "\n")
            _openssl("genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", f"{stem}-key.pem", cwd=work)
            _openssl("req", "-new", "-key", f"{stem}-key.pem", "-subj", f"/O=TrackGraph test/CN={cn}", "-out", f"{stem}.csr", cwd=work)
            _openssl(
                "x509", "-req", "-in", f"{stem}.csr", "-CA", "ca.pem", "-CAkey", "ca-key.pem",
                "-set_serial", str(int.from_bytes(os.urandom(8), "big")), "-days", str(days),
                "-sha256", "-extfile", f"{stem}.ext", "-out", f"{stem}.pem",
                cwd=work,
            )  # fmt: skip

        leaf("server", hosts[0], hosts, "serverAuth")
        stems = ["ca", "server"] + [f"client-{c}" for c in clients]
        for c in clients:
            leaf(f"client-{c}", c, [], "clientAuth")
        for stem in stems:
            (out / f"{stem}.pem").write_bytes((work / f"{stem}.pem").read_bytes())
            _write_private(out / f"{stem}-key.pem", (work / f"{stem}-key.pem").read_bytes())


def _req_config(work: Path) -> Path:
    path = work / "req.cnf"
    path.write_text(
        "[req]\ndistinguished_name=dn\nprompt=no\n[dn]\n"
        "[v3_ca_tg]\nbasicConstraints=critical,CA:TRUE,pathlen:0\n"
        "keyUsage=critical,digitalSignature,keyCertSign,cRLSign\nsubjectKeyIdentifier=hash\n"
    )
    return path


# --------------------------------------------------------------------------- entry points


def make_certs(
    out: str | Path,
    *,
    hosts: list[str] | tuple[str, ...] = DEFAULT_HOSTS,
    clients: list[str] | tuple[str, ...] = (),
    days: int = 30,
    backend: str = "auto",
) -> dict[str, str]:
    """Write the CA, server and client certificates into ``out``; return name -> path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    hosts = list(dict.fromkeys(hosts)) or list(DEFAULT_HOSTS)
    clients = list(dict.fromkeys(clients))
    for c in clients:
        if not c or not all(ch.isascii() and (ch.isalnum() or ch in "-_.") for ch in c):
            raise ValueError(f"client name {c!r}: use letters, digits, '-', '_' or '.'")
    for h in hosts:
        if not _is_ip(h) and not all(ch.isascii() and (ch.isalnum() or ch in "-.") for ch in h):
            raise ValueError(f"host {h!r}: expected a DNS name or an IP address")
    if backend == "auto":
        backend = "cryptography" if _have_cryptography() else "openssl"
    if backend == "cryptography":
        _make_with_cryptography(out, hosts, clients, days)
    elif backend == "openssl":
        _make_with_openssl(out, hosts, clients, days)
    else:
        raise ValueError(f"unknown backend {backend!r}: expected auto, cryptography or openssl")
    files = {"ca": out / "ca.pem", "ca_key": out / "ca-key.pem", "server": out / "server.pem", "server_key": out / "server-key.pem"}
    for c in clients:
        files[f"client_{c}"] = out / f"client-{c}.pem"
        files[f"client_{c}_key"] = out / f"client-{c}-key.pem"
    return {"backend": backend, **{k: str(v) for k, v in files.items()}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out", nargs="?", type=Path, default=DEFAULT_OUT, help=f"output folder (default {DEFAULT_OUT})")
    p.add_argument("--host", action="append", default=[], metavar="NAME_OR_IP", help="extra server name or address (repeatable); localhost and 127.0.0.1 are always included")
    p.add_argument("--client", action="append", default=[], metavar="NAME", help="also make a client certificate with this common name (repeatable), for mutual TLS")
    p.add_argument("--days", type=int, default=30, help="validity in days (default 30)")
    p.add_argument("--backend", choices=["auto", "cryptography", "openssl"], default="auto")
    p.add_argument("--force", action="store_true", help="overwrite existing files in OUT")
    p.add_argument("--json", action="store_true", help="print the paths as JSON")
    args = p.parse_args(argv)
    if args.days < 1:
        p.error("--days must be at least 1")
    if (args.out / "ca.pem").exists() and not args.force:
        print(f"make_certs: {args.out / 'ca.pem'} exists; pass --force to replace it", file=sys.stderr)
        return 2
    try:
        files = make_certs(args.out, hosts=[*DEFAULT_HOSTS, *args.host], clients=args.client, days=args.days, backend=args.backend)
    except (RuntimeError, ValueError) as exc:
        print(f"make_certs: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(files))
    else:
        print(f"wrote certificates with {files['backend']} into {Path(args.out).resolve()}:")
        for k, v in files.items():
            if k != "backend":
                print(f"  {k:<24} {v}")
        print("keep ca-key.pem and the *-key.pem files private; they are throwaway test credentials")
    return 0


if __name__ == "__main__":
    sys.exit(main())
