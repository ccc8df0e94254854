"""Mutual TLS: certificates we generate, and a TLS scheduler + workers that refuse strangers."""

from __future__ import annotations

import asyncio
import gc
import shutil
import socket
import ssl
import stat
import subprocess
import threading
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec
from distributed import Client
from distributed.comm import connect
from distributed.comm.core import CommClosedError

from schlieren.workers.cli import main as cli_main
from schlieren.workers.cluster import ClusterOptions, open_client
from schlieren.workers.security import (
    ROLES,
    TLSFiles,
    cluster_security,
    make_certificates,
    make_security,
    tls_files_from_config,
)

REPO = Path(__file__).resolve().parents[2]


def _handshake(server_files: TLSFiles, client_ctx: ssl.SSLContext) -> None:
    """Mutual-TLS handshake over a loopback socket pair; raises ssl.SSLError on refusal."""
    server_ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH, cafile=str(server_files.ca_file))
    server_ctx.load_cert_chain(str(server_files.cert), str(server_files.key))
    server_ctx.verify_mode = ssl.CERT_REQUIRED
    a, b = socket.socketpair()
    errors: list[BaseException] = []

    def serve() -> None:
        try:
            with server_ctx.wrap_socket(a, server_side=True) as s:
                s.sendall(b"ok")
        except (ssl.SSLError, OSError) as exc:
            errors.append(exc)

    t = threading.Thread(target=serve)
    t.start()
    try:
        with client_ctx.wrap_socket(b, server_hostname="127.0.0.1") as c:
            assert c.recv(2) == b"ok"
    finally:
        t.join(10)
        a.close()
        b.close()
    if errors:
        raise errors[0]


def _client_ctx(files: TLSFiles | None, ca_file: Path) -> ssl.SSLContext:
    ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(ca_file))
    ctx.check_hostname = False
    if files is not None:
        ctx.load_cert_chain(str(files.cert), str(files.key))
    return ctx


def test_make_certificates_layout_and_chain(tmp_path):
    certs = make_certificates(tmp_path / "tls", hosts=["127.0.0.1", "localhost", "node01"])
    ca = x509.load_pem_x509_certificate(certs.ca_file.read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for role in ROLES:
        files = certs.files(role)
        cert = x509.load_pem_x509_certificate(files.cert.read_bytes())
        assert cert.issuer == ca.subject
        # raises InvalidSignature unless the CA signed it
        ca.public_key().verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(cert.signature_hash_algorithm))
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert [str(ip) for ip in san.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
        assert san.get_values_for_type(x509.DNSName) == ["localhost", "node01"]
        assert stat.S_IMODE(files.key.stat().st_mode) == 0o600
    assert stat.S_IMODE(certs.ca_key.stat().st_mode) == 0o600
    with pytest.raises(FileExistsError):
        make_certificates(tmp_path / "tls")


def test_certificates_do_mutual_tls_and_refuse_strangers(tmp_path):
    ours = make_certificates(tmp_path / "ours")
    theirs = make_certificates(tmp_path / "theirs")
    server = ours.files("scheduler")
    _handshake(server, _client_ctx(ours.files("client"), ours.ca_file))  # works
    with pytest.raises((ssl.SSLError, OSError)):
        _handshake(server, _client_ctx(None, ours.ca_file))  # no client certificate
    with pytest.raises((ssl.SSLError, OSError)):
        _handshake(server, _client_ctx(theirs.files("client"), ours.ca_file))  # another CA's certificate


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl binary not installed")
def test_make_certs_script_output_works_for_mutual_tls(tmp_path):
    out = tmp_path / "sh"
    subprocess.run(
        ["bash", str(REPO / "deploy/tls/make-certs.sh"), str(out), "127.0.0.1", "localhost"],
        check=True, capture_output=True, timeout=60,
    )
    for role in ROLES:
        assert (out / f"{role}.pem").is_file() and stat.S_IMODE((out / f"{role}-key.pem").stat().st_mode) == 0o600
    files = TLSFiles.from_dir(out, "scheduler")
    _handshake(files, _client_ctx(TLSFiles.from_dir(out, "client"), out / "ca.pem"))
    with pytest.raises((ssl.SSLError, OSError)):
        _handshake(files, _client_ctx(None, out / "ca.pem"))
    sec = cluster_security(out)  # distributed accepts the files for every role
    assert sec.require_encryption and sec.tls_worker_cert == str(out / "worker.pem")
    again = subprocess.run(["bash", str(REPO / "deploy/tls/make-certs.sh"), str(out)], capture_output=True, timeout=60)
    assert again.returncode != 0 and b"exists" in again.stderr


def test_tls_config_forms(tmp_path):
    d = tmp_path / "c"
    assert tls_files_from_config({"dir": str(d)}, "worker") == TLSFiles(d / "ca.pem", d / "worker.pem", d / "worker-key.pem")
    explicit = {"ca-file": "a.pem", "cert": "b.pem", "key": "c.pem"}
    assert tls_files_from_config(explicit) == TLSFiles(Path("a.pem"), Path("b.pem"), Path("c.pem"))
    with pytest.raises(ValueError, match="missing key"):
        tls_files_from_config({"ca-file": "a.pem", "cert": "b.pem"})
    with pytest.raises(ValueError, match="unknown"):
        tls_files_from_config({"dir": "x", "password": "y"})
    with pytest.raises(FileNotFoundError, match="CA file"):
        make_security(TLSFiles.from_dir(d, "client"))


def test_tls_init_command(tmp_path, capsys):
    assert cli_main(["tls", "init", str(tmp_path / "t"), "--host", "127.0.0.1", "--host", "sched.lab"]) == 0
    cert = x509.load_pem_x509_certificate((tmp_path / "t/worker.pem").read_bytes())
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.DNSName) == ["sched.lab"]
    assert str(tmp_path / "t") in capsys.readouterr().out
    assert cli_main(["tls", "init", str(tmp_path / "t")]) == 2  # refuses to replace a CA


async def _raw_tls_connect(address: str, ctx: ssl.SSLContext) -> None:
    comm = await connect(address, timeout=5, ssl_context=ctx, require_encryption=True)
    try:
        # the scheduler verifies the client's certificate during the handshake; TLS 1.3
        # reports a refusal on the first read
        await comm.write({"op": "identity"})
        await comm.read()
    finally:
        comm.abort()


async def _async_client(address: str, security) -> None:
    client = await Client(address, security=security, timeout=5, asynchronous=True)
    await client.close()  # only reached if the scheduler accepted us


@pytest.mark.timeout(120)
@pytest.mark.filterwarnings("ignore:coroutine .* was never awaited:RuntimeWarning")
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # refused clients' __del__
def test_tls_cluster_accepts_certified_client_and_refuses_others(tmp_path, external_cluster_factory):
    certs = make_certificates(tmp_path / "tls")
    strangers = make_certificates(tmp_path / "strangers")
    cluster = external_cluster_factory(n_workers=2, tls_dir=certs.directory)
    assert cluster.address.startswith("tls://127.0.0.1:")

    # with the project's client certificate: works, through our own entry point
    with open_client(ClusterOptions(scheduler=cluster.address, tls_dir=str(certs.directory), connect_timeout=30)) as (
        client,
        info,
    ):
        assert info.n_workers == 2 and info.tomo_slots == 2
        assert all(addr.startswith("tls://127.0.0.1:") for addr in client.scheduler_info()["workers"])
        assert client.submit(sum, [1, 2, 3], key="deflection-tls-000000").result(timeout=30) == 6

    # without any certificate the client cannot even open a TLS comm
    with pytest.raises(TypeError, match="ssl_context"):
        asyncio.run(_async_client(cluster.address, None))
    # speaking TLS but presenting no certificate: the scheduler refuses the handshake
    with pytest.raises((CommClosedError, OSError, ssl.SSLError)):
        asyncio.run(_raw_tls_connect(cluster.address, _client_ctx(None, certs.ca_file)))
    # a certificate from another CA: refused
    with pytest.raises(CommClosedError, match="certificate"):
        asyncio.run(_async_client(cluster.address, make_security(strangers.files("client"))))
    # plain TCP to the TLS port: refused
    with pytest.raises((CommClosedError, OSError)):
        asyncio.run(_async_client(cluster.address.replace("tls://", "tcp://"), None))
    gc.collect()  # distributed leaves an un-awaited coroutine per refused client; warn here, not later
    # our options refuse certificates for a tcp:// scheduler address
    with pytest.raises(ValueError, match="not tls"):
        with open_client(ClusterOptions(scheduler=cluster.address.replace("tls://", "tcp://"), tls_dir=str(certs.directory))):
            pass


@pytest.mark.system
@pytest.mark.timeout(120)
def test_local_cluster_with_tls(tmp_path):
    certs = make_certificates(tmp_path / "tls")
    opts = ClusterOptions(workers=1, tls_dir=str(certs.directory), memory_limit="1GiB", dashboard_address="127.0.0.1:0")
    with open_client(opts) as (client, info):
        assert info.scheduler_address.startswith("tls://127.0.0.1:")
        assert all(a.startswith("tls://127.0.0.1:") for a in client.scheduler_info()["workers"])
        assert client.submit(max, [3, 9, 4], key="tomography-ltls-000000", resources={"TOMO": 1}).result(timeout=30) == 9
    with pytest.raises(ValueError, match="--tls DIR"):
        with open_client(ClusterOptions(workers=1, tls_ca_file="a", tls_cert="b", tls_key="c")):
            pass


@pytest.mark.timeout(180)
def test_tls_mistakes_are_one_line_errors(tmp_path, external_cluster_factory, tiny_session):
    """A missing --tls, a tcp:// address for a TLS scheduler, certificates of another CA and
    a certificate folder that does not exist: one line naming the scheduler, exit code 2."""
    import subprocess
    import sys

    certs = make_certificates(tmp_path / "tls")
    strangers = make_certificates(tmp_path / "strangers")
    cluster = external_cluster_factory(n_workers=1, tls_dir=certs.directory)
    addr = cluster.address
    run = [sys.executable, "-m", "schlieren.workers.cli", "run", str(tiny_session.session),
           "--out", str(tmp_path / "o.zarr"), "--no-progress"]
    cases = {
        "no --tls": (["--scheduler", addr], "--tls DIR"),
        "tcp:// for a TLS scheduler": (["--scheduler", addr.replace("tls://", "tcp://")], "give its tls:// address"),
        "another CA": (["--scheduler", addr, "--tls", str(strangers.directory)], "not from this cluster's CA"),
        "no such folder": (["--scheduler", addr, "--tls", str(tmp_path / "nope")], "nope/ca.pem"),
    }
    for name, (extra, hint) in cases.items():
        proc = subprocess.run(run + extra, capture_output=True, text=True, timeout=120)
        err = proc.stderr.strip()
        assert proc.returncode == 2, (name, err)
        assert "Traceback" not in err and len(err.splitlines()) == 1, (name, err)
        assert err.startswith("schlieren run: error:") and hint in err, (name, err)
        assert addr.split("://")[1] in err or name == "no such folder", (name, err)
    assert not (tmp_path / "o.zarr").exists()
