"""``make run``: the service on the simulated cell, and the example cell controller driving it.

Starts ``flyscan serve --sim`` and, once it answers, ``python -m clients.cell_controller``
scanning until Ctrl-C; prints where to look. Ctrl-C (or either process ending) stops both.
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
import urllib.request

START_TIMEOUT_S = 120.0


def wait_healthy(url: str, server: subprocess.Popen) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if server.poll() is not None:
            sys.exit(f"make run: the service exited with status {server.returncode}")
        try:
            with urllib.request.urlopen(f"{url}/health", timeout=1.0) as response:
                if response.status == 200:
                    return
        except OSError:
            time.sleep(0.3)
    sys.exit(f"make run: the service did not answer on {url} within {START_TIMEOUT_S:.0f} s")


def stop(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(15)
        except (subprocess.TimeoutExpired, KeyboardInterrupt):  # a second Ctrl-C: no waiting
            process.kill()
            process.wait()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument("--zmq-port", type=int, default=5556)
    parser.add_argument("--data", default="out/service")
    parser.add_argument("--count", type=int, default=0, help="scans; 0: until Ctrl-C")
    args = parser.parse_args()
    # `kill` and `timeout` stop the demo as Ctrl-C does: both children are stopped cleanly.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    url, zmq = f"http://127.0.0.1:{args.port}", f"tcp://127.0.0.1:{args.zmq_port}"
    bin_dir = os.path.dirname(sys.executable)
    # The children run in sessions of their own: Ctrl-C reaches this script alone, which stops
    # the controller first and then the service, each with one SIGINT.
    server = subprocess.Popen([os.path.join(bin_dir, "flyscan"), "serve", "--sim", "--port",
                               str(args.port), "--zmq", zmq, "--data", args.data],
                              start_new_session=True)
    controller = None
    try:
        wait_healthy(url, server)
        print(f"\n  status page:  {url}/\n  REST API:     {url}/docs\n  clouds:       {zmq} "
              f"(ZeroMQ)\n  scans stored: {os.path.abspath(args.data)}/scans\n\n"
              "  the example cell controller now arms scan after scan; Ctrl-C stops both\n",
              flush=True)
        controller = subprocess.Popen([sys.executable, "-m", "clients.cell_controller", "--url",
                                       url, "--zmq", zmq, "--count", str(args.count)],
                                      start_new_session=True)
        while controller.poll() is None and server.poll() is None:
            time.sleep(0.2)
        return controller.returncode or server.returncode or 0
    except KeyboardInterrupt:
        return 0
    finally:
        if controller is not None:
            stop(controller)
        stop(server)


if __name__ == "__main__":
    sys.exit(main())
