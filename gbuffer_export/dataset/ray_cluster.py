"""Connecting ``blendsr dataset --executor ray`` to a Ray cluster: within a time limit, and with one line naming
``--address`` (and ``RAY_AUTH_MODE`` where authentication may be the cause) when it cannot (pure Python; Ray is
imported only here, when a Ray run starts).

Ray's own ``ray.init(address=HOST:PORT)`` retries without end when nothing answers there, and a cluster with token
authentication (Ray 2.60 writes ``~/.ray/auth_token`` on a local ``ray.init()`` and then starts ``ray start --head``
clusters with token authentication) refuses a driver without ``RAY_AUTH_MODE=token`` after 20 s of retries with a
bare ``ConnectionError``. ``connect`` therefore checks the address's form, opens a TCP connection to it first (at
most ``PROBE_S`` seconds) and bounds Ray's own GCS connection (``GCS_ENV``, unless set already) before it calls
``ray.init``; every failure is a ``RayConnectError`` (one line, exit 2 through the CLI).
"""
from __future__ import annotations

import contextlib
import os
import socket
from pathlib import Path

from ..errors import BlendSRError

#: Seconds a TCP connection to the cluster's address may take before it counts as nothing listening.
PROBE_S = 5.0

#: Ray's settings (environment, read by ``ray.init``) that bound its connection to an existing cluster's GCS:
#: one attempt of about 15 s instead of retries without end. Set only for an explicit address, only when unset, and
#: before ``import ray`` (a process that imported Ray earlier keeps Ray's defaults).
GCS_ENV = {"RAY_gcs_server_port_wait_time_s": "1", "RAY_gcs_rpc_server_reconnect_timeout_s": "5",
           "RAY_py_gcs_connect_timeout_s": "5"}

FORMS = "HOST:PORT (a cluster's GCS, e.g. 10.0.0.1:6379), auto (the cluster this machine has joined) or " \
        "ray://HOST:10001 (Ray Client)"


class RayConnectError(BlendSRError):
    """The Ray cluster at ``--address`` cannot be used: one line naming the address."""


def parse_host_port(address: str, what: str) -> tuple[str, int]:
    """(host, port) of ``HOST:PORT`` (an IPv6 host in brackets); RayConnectError naming ``what`` otherwise."""
    host, sep, port = address.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or any(c.isspace() for c in host) or (":" in host and not address.startswith("[")):
        raise RayConnectError(f"{what}: not a Ray address; give {FORMS}")
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise RayConnectError(f"{what}: port {port!r} is not a number from 1 to 65535; give {FORMS}")
    return host, int(port)


def probe(host: str, port: int, what: str, timeout: float = PROBE_S) -> None:
    """A TCP connection to host:port within ``timeout`` seconds; RayConnectError naming ``what`` otherwise."""
    try:
        with socket.create_connection((host, port), timeout=timeout):
            pass
    except socket.timeout:
        raise RayConnectError(f"{what}: no answer within {timeout:g} s (is the Ray head running and reachable? "
                              "start one with 'ray start --head')") from None
    except OSError as exc:
        raise RayConnectError(f"{what}: cannot connect ({exc.strerror or exc}); is the Ray head running there? "
                              "(start one with 'ray start --head')") from None


def token_hint() -> str:
    """What to say about token authentication: RAY_AUTH_MODE=token, and the token this machine holds."""
    mode = os.environ.get("RAY_AUTH_MODE")
    if mode and mode.lower() == "token":
        return ("RAY_AUTH_MODE=token is set: check that this machine has the cluster's token (~/.ray/auth_token, "
                "$RAY_AUTH_TOKEN_PATH or $RAY_AUTH_TOKEN)")
    token = os.environ.get("RAY_AUTH_TOKEN_PATH") or str(Path.home() / ".ray" / "auth_token")
    has = bool(os.environ.get("RAY_AUTH_TOKEN")) or Path(token).is_file()
    return ("a cluster with token authentication (Ray's default once a token exists" +
            (f"; this machine has one in {token}" if has else "") +
            ") needs RAY_AUTH_MODE=token in the environment of this command")


def check_address(address: str) -> tuple[str, tuple[str, int] | None]:
    """The address's kind ('client', 'auto' or 'gcs') and its (host, port) when it names one; RayConnectError for
    a malformed one or a Ray Client address without the ``ray[client]`` package."""
    what = f"--address {address}"
    if address == "auto":
        return "auto", None
    if address.startswith("ray://"):
        from ray._private.utils import get_ray_client_dependency_error
        if get_ray_client_dependency_error() is not None:
            raise RayConnectError(f"{what}: a Ray Client address (ray://) needs the 'ray[client]' package "
                                  "(pip install 'ray[client]'), or give the cluster's GCS address HOST:6379")
        return "client", parse_host_port(address[len("ray://"):], what)
    if "://" in address:
        raise RayConnectError(f"{what}: not a Ray address; give {FORMS}")
    return "gcs", parse_host_port(address, what)


def bound_gcs_connection(address: str | None) -> None:
    """``GCS_ENV`` into this process's environment for an explicit address (call it before ``import ray``)."""
    if address is not None:
        for k, v in GCS_ENV.items():
            os.environ.setdefault(k, v)


def connect(address: str | None, runtime_env: dict) -> bool:
    """``ray.init`` on the cluster at ``address`` (None: start a local one); True when this call initialised Ray
    (the caller shuts it down). RayConnectError (one line naming the address) when the cluster cannot be reached
    or refuses this driver."""
    bound_gcs_connection(address)
    import ray
    if ray.is_initialized():
        return False
    if address is None:
        ray.init(address="local", include_dashboard=False, log_to_driver=False, runtime_env=runtime_env)
        return True
    kind, host_port = check_address(address)
    what = f"--address {address}"
    if host_port is not None:
        probe(*host_port, what)
    auth_error = getattr(ray.exceptions, "AuthenticationError", ())  # Ray >= 2.52
    try:
        ray.init(address=address, include_dashboard=False, log_to_driver=False, runtime_env=runtime_env)
    except auth_error as exc:
        raise RayConnectError(f"{what}: the Ray cluster refused this driver's token "
                              f"({getattr(exc, 'message', None) or _first(exc)}); "
                              f"{token_hint()}") from None
    except ConnectionError as exc:
        if kind == "auto" and "Could not find any running Ray instance" in str(exc):
            raise RayConnectError(f"{what}: no running Ray cluster found on this machine (start one with "
                                  "'ray start --head', or give its address as HOST:PORT)") from None
        with contextlib.suppress(Exception):
            ray.shutdown()
        port = "its Ray Client server port (10001 by default)" if kind == "client" else \
            "the head's GCS port (6379 by default)"
        raise RayConnectError(f"{what}: the Ray cluster there did not accept this driver ({_first(exc)}); "
                              f"{token_hint()}, and the address must be {port}") from None
    except ValueError as exc:  # Ray's own address checks
        raise RayConnectError(f"{what}: {_first(exc)}; give {FORMS}") from None
    return True


def _first(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0].rstrip(".") if text else type(exc).__name__


__all__ = ["GCS_ENV", "PROBE_S", "RayConnectError", "bound_gcs_connection", "check_address", "connect",
           "parse_host_port", "probe"]
