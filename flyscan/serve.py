"""``flyscan serve``: the real-time scanning service, with real devices or, with ``--sim``,
the simulated cell's (``flyscan.simdevices``: the only place they are wired in)."""
from __future__ import annotations

from pathlib import Path

from flyscan.common import UsageError

__all__ = ["add_parser", "run", "service_for", "load_serve_settings"]

#: Seconds a stopping service waits for open connections (server-sent events) to close.
SHUTDOWN_GRACE_S = 3.0


def add_parser(command) -> None:
    serve = command("serve", help="run the real-time scanning service (REST, ZeroMQ, "
                                  "status page)")
    serve.add_argument("--config", type=Path, default=None, help="settings file (TOML)")
    serve.add_argument("--sim", action="store_true", default=None,
                       help="simulated devices: the reference cell with its camera and robot")
    serve.add_argument("--host", default=None, help="REST bind address (default 127.0.0.1)")
    serve.add_argument("--port", type=int, default=None, help="REST port (default 8000)")
    serve.add_argument("--zmq", default=None, help="ZeroMQ PUB endpoint (default tcp://127.0.0.1:5556)")
    serve.add_argument("--robot", default=None,
                       help="ur://HOST: the UR robot (ur-rtde); with --sim an RTDE emulator "
                            "is started at HOST and serves the simulated robot")
    serve.add_argument("--camera", default=None,
                       help="opencv:0, opencv:/dev/videoN, video:FILE, gstreamer:PIPELINE, "
                            "genicam:PRODUCER.cti[#SERIAL], pylon:[SERIAL][?options] or "
                            "replay:FOLDER (not with --sim)")
    serve.add_argument("--calibration", type=Path, default=None,
                       help="calibration JSON (flyscan calibrate); default the one kept in the "
                            "data folder (PUT /calibration), or with --sim the cell's truth")
    serve.add_argument("--data", type=Path, default=None, help="folder for scans and parts "
                                                               "(default ./flyscan-data)")
    serve.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])


def service_for(settings, sim=None):
    """The service of ``settings``: its devices real, or with ``sim``
    (``flyscan.simdevices.SimSettings`` saying ``sim``) the simulated cell's."""
    from service.daemon import Service

    if sim is None or not sim.sim:
        return Service(settings)
    if settings.camera is not None:
        raise ValueError(f"--camera {settings.camera}: the simulated cell has its own camera")
    from flyscan.simdevices import simulated_devices

    return Service(settings, devices=simulated_devices(sim, settings.robot))


def load_serve_settings(config, *, sim=None, **overrides):
    """(the service's ``Settings``, the simulated cell's ``SimSettings``) from the settings
    file ``config`` (or None), the environment and the command line's ``overrides``."""
    from flyscan.simdevices import load_sim_settings, split_sim_settings
    from service.settings import load_settings, read_settings_file

    service_part, sim_part = split_sim_settings(
        read_settings_file(config) if config is not None else {})
    return load_settings(service_part, **overrides), load_sim_settings(sim_part, sim=sim)


def run(args) -> int:
    import logging

    import uvicorn
    from pydantic import ValidationError

    from service.api import create_app
    from service.connections import (ACCEPT_BACKLOG, connection_bound, guarded_protocol,
                                     open_files, quiet_crowding, raise_file_limit)
    try:
        settings, sim = load_serve_settings(
            args.config, sim=args.sim, host=args.host, port=args.port, zmq=args.zmq,
            robot=args.robot, camera=args.camera, calibration=args.calibration, data=args.data)
        service = service_for(settings, sim)
    except FileNotFoundError as exc:
        raise UsageError(str(exc)) from None
    except ValidationError as exc:
        first = exc.errors()[0]
        raise UsageError(f"setting {'.'.join(map(str, first['loc']))}: {first['msg']}") from None
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    _check_addresses(settings)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(name)s: %(message)s")
    url = f"http://{settings.host}:{settings.port}/"
    print(f"flyscan serve: status page {url}, REST {url}docs, ZeroMQ {settings.zmq}, "
          f"data {settings.data.resolve()}{' (simulated cell)' if sim.sim else ''}",
          flush=True)
    soft_files, _ = raise_file_limit()
    quiet_crowding()
    protocol = guarded_protocol(settings.header_timeout_s,
                                connection_bound(settings.max_connections, soft_files,
                                                 open_files()))
    # Open event streams (a status page left open) must not hold up a Ctrl-C for ever.
    config = uvicorn.Config(create_app(service=service), host=settings.host, port=settings.port,
                            log_level=args.log_level, access_log=False, http=protocol,
                            backlog=ACCEPT_BACKLOG,
                            timeout_graceful_shutdown=SHUTDOWN_GRACE_S)
    server = uvicorn.Server(config)
    try:
        server.run()
    except KeyboardInterrupt:  # uvicorn re-raises Ctrl-C once it has shut down cleanly
        pass
    return 0 if server.started else 2


def _check_addresses(settings) -> None:
    """Both addresses free before anything starts: a clear error, not a start-up traceback."""
    import socket

    import zmq

    try:
        with socket.create_server((settings.host, settings.port)):
            pass
    except OSError as exc:
        raise UsageError(f"cannot serve HTTP on {settings.host}:{settings.port}: {exc.strerror}") from None
    probe = zmq.Context.instance().socket(zmq.PUB)
    try:
        probe.bind(settings.zmq)
    except zmq.ZMQError as exc:
        raise UsageError(f"cannot bind the ZeroMQ publisher to {settings.zmq}: {exc}") from None
    finally:
        probe.close(linger=0)
