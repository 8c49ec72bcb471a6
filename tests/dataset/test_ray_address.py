"""``blendsr dataset --executor ray --address ...`` that cannot connect: one line naming the address, exit 2, within
a bounded time (issue 43 items 4-5, issue 42 finding 3): a malformed address, a Ray Client address without
``ray[client]``, ``auto`` with no cluster, nothing listening (a runaway before), a port that answers but is no Ray
cluster, and a cluster with token authentication (naming RAY_AUTH_MODE=token). Loopback (127.0.0.1) only; every
Ray process started here is this test's and is shut down by it."""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.conftest import ENV, REPO

pytest.importorskip("ray")

SPEC = """[dataset]
name = "r"
[render]
frames = 1
hr_size = "64x32"
[[source]]
name = "b"
kind = "builtin"
seeds = "0:0"
cameras = ["scene"]
"""


@pytest.fixture()
def ray_env(tmp_path):
    """A HOME of the test's own (Ray writes ~/.ray there) and loopback-only Ray."""
    home = tmp_path / "home"
    home.mkdir()
    env = {k: v for k, v in ENV.items() if not k.startswith("RAY_")}
    env.update(HOME=str(home), RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER="0")
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC)
    return env, spec


def _dataset(env, spec: Path, out: Path, address: str, timeout=120, code_before="") -> tuple[int, str, float]:
    """``main(["dataset", ..., "--address", address])`` in a fresh Python (after ``code_before``): (exit, stderr,
    seconds)."""
    code = (f"import sys\n{code_before}\nfrom gbuffer_export.cli import main\n"
            f"sys.exit(main(['dataset', {str(spec)!r}, '-o', {str(out)!r}, '--executor', 'ray', '--address', "
            f"{address!r}, '--no-progress']))\n")
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=timeout)
    return proc.returncode, proc.stderr, time.perf_counter() - t0


#: Ray's GCS connection bounds for the test that waits them out (a port that answers but is no Ray cluster): 1 s
#: instead of the product's GCS_ENV and Ray's default of 5 s for the first connection, which the command keeps when
#: they are set already (about 4 s of connecting instead of 12 s). That the command sets its own bounds:
#: test_an_explicit_address_bounds_the_gcs_connection.
SHORT_GCS = {"RAY_gcs_rpc_server_reconnect_timeout_s": "1", "RAY_py_gcs_connect_timeout_s": "1",
             "RAY_gcs_rpc_server_connect_timeout_s": "1"}


def test_an_explicit_address_bounds_the_gcs_connection(monkeypatch):
    """``bound_gcs_connection`` sets every GCS_ENV bound for an explicit address (about 15 s in all), keeps a value
    the user set, and sets nothing for a local instance."""
    from gbuffer_export.dataset import ray_cluster
    for k in ray_cluster.GCS_ENV:
        monkeypatch.delenv(k, raising=False)
    ray_cluster.bound_gcs_connection(None)
    assert not any(k in os.environ for k in ray_cluster.GCS_ENV)
    monkeypatch.setenv("RAY_py_gcs_connect_timeout_s", "2")
    ray_cluster.bound_gcs_connection("127.0.0.1:6379")
    assert os.environ["RAY_py_gcs_connect_timeout_s"] == "2"
    for k, v in ray_cluster.GCS_ENV.items():
        assert k == "RAY_py_gcs_connect_timeout_s" or os.environ[k] == v
        assert 0 < float(v) <= 5, (k, v)


def _one_line_error(err: str) -> str:
    assert "Traceback" not in err, err[-3000:]
    lines = [ln for ln in err.splitlines() if ln.startswith("blendsr: error:")]
    assert len(lines) == 1, err[-3000:]
    return lines[0]


@pytest.mark.parametrize("address", ["not an address", "127.0.0.1:99999", "127.0.0.1:1:2", "http://127.0.0.1:1",
                                     "127.0.0.1:"])
def test_a_malformed_address_is_refused_before_anything_is_written(ray_env, tmp_path, address):
    env, spec = ray_env
    code, err, _ = _dataset(env, spec, tmp_path / "ds", address)
    assert code == 2 and f"--address {address}:" in _one_line_error(err)
    assert not (tmp_path / "ds").exists()


def test_a_ray_client_address_without_ray_client_names_the_package(ray_env, tmp_path):
    env, spec = ray_env
    code, err, _ = _dataset(env, spec, tmp_path / "ds", "ray://127.0.0.1:10001", code_before=(
        "import ray._private.utils as u; u.get_ray_client_dependency_error = lambda: ImportError('grpc')"))
    line = _one_line_error(err)
    assert code == 2 and "--address ray://127.0.0.1:10001" in line and "ray[client]" in line


def test_auto_without_a_cluster_is_one_line(ray_env, tmp_path):
    env, spec = ray_env
    # no cluster of this test's (another Ray on a shared machine must not be found: its discovery is stubbed)
    code, err, took = _dataset(env, spec, tmp_path / "ds", "auto", code_before=(
        "import functools, ray._private.services as s; s.find_gcs_addresses = functools.lru_cache(lambda: []); "
        "s.find_bootstrap_address = lambda *a, **k: None"))
    line = _one_line_error(err)
    assert code == 2 and "--address auto" in line and "no running Ray cluster" in line and took < 60


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_nothing_listening_is_refused_within_seconds(ray_env, tmp_path):
    env, spec = ray_env
    port = _free_port()
    code, err, took = _dataset(env, spec, tmp_path / "ds", f"127.0.0.1:{port}", timeout=90)
    line = _one_line_error(err)
    assert code == 2 and f"--address 127.0.0.1:{port}" in line and took < 30, (took, line)


def test_a_port_that_is_no_ray_cluster_is_refused_in_bounded_time(ray_env, tmp_path):
    """A port that accepts and says nothing: Ray's own GCS connection ends within its bounds (SHORT_GCS here) and
    the command says one line naming the address and RAY_AUTH_MODE."""
    env, spec = ray_env
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(16)
    port = server.getsockname()[1]
    held = []
    stop = threading.Event()

    def accept():  # accepts and says nothing, as a stuck or foreign service would
        server.settimeout(0.2)
        while not stop.is_set():
            try:
                held.append(server.accept()[0])
            except OSError:
                pass
    t = threading.Thread(target=accept, daemon=True)
    t.start()
    try:
        code, err, took = _dataset({**env, **SHORT_GCS}, spec, tmp_path / "ds", f"127.0.0.1:{port}", timeout=150)
    finally:
        stop.set()
        t.join(2)
        for c in held:
            c.close()
        server.close()
    line = _one_line_error(err)
    assert code == 2 and f"--address 127.0.0.1:{port}" in line and "RAY_AUTH_MODE" in line
    assert took < 90, took


HEAD = """
import sys
from ray.cluster_utils import Cluster
cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
print(cluster.address, flush=True)
sys.stdin.read()  # until the test closes it
cluster.shutdown()
"""


def test_a_token_authenticated_cluster_is_one_line_naming_ray_auth_mode(ray_env, tmp_path):
    """Ray 2.60 turns token authentication on for clusters once ~/.ray/auth_token exists (a local ray.init()
    writes it); a driver without RAY_AUTH_MODE=token is refused by such a cluster."""
    env, spec = ray_env
    gen = pytest.importorskip("ray._private.authentication.authentication_token_generator",
                              reason="this Ray has no token authentication (added in Ray 2.52)")
    generate_new_authentication_token = gen.generate_new_authentication_token
    (Path(env["HOME"]) / ".ray").mkdir()
    (Path(env["HOME"]) / ".ray" / "auth_token").write_text(generate_new_authentication_token())
    head = subprocess.Popen([sys.executable, "-c", HEAD], cwd=REPO, env={**env, "RAY_AUTH_MODE": "token"},
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        address = head.stdout.readline().strip()
        assert address.startswith("127.0.0.1:"), address
        code, err, took = _dataset(env, spec, tmp_path / "ds", address, timeout=150)
    finally:
        head.stdin.close()
        try:
            head.wait(60)
        except subprocess.TimeoutExpired:
            head.kill()
            head.wait()
    line = _one_line_error(err)
    assert code == 2 and f"--address {address}" in line and "RAY_AUTH_MODE=token" in line, line
    assert took < 60, took
