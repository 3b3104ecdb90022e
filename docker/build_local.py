#!/usr/bin/env python3
"""docker/Dockerfile built and run for real, without a Docker engine or an image registry.

Debian's archive and PyPI are all this needs. As root:

1. the base: a Debian bookworm made by ``debootstrap`` (minbase, with python3-venv) and a venv
   at /opt/venv first on the PATH, so that it looks like ``python:3.11-slim`` (``python`` and
   ``pip`` on the PATH, Python 3.11), committed with ``buildah``. Its root file system is kept
   as a tar under ``--cache-dir`` for the rest of the UTC day, so another run that day skips
   debootstrap;
2. the image: ``buildah bud`` on docker/Dockerfile with ``--build-arg BASE_IMAGE=`` that base;
   pip inside the build is given the machine's CA bundle (``$PIP_CERT``, else
   /etc/ssl/certs/ca-certificates.crt) by a pip.conf mounted read-only for the build only;
3. the container: the image's own entry point and command (``flyscan serve --sim``) run by
   ``buildah run --isolation chroot --network host``, with the command's host and ports moved
   to free ports on the loopback; ``/health`` waited for;
4. a scan armed over REST (``POST /scans``), waited for until done, its cloud fetched;
5. the user: every process of the server runs as the image's USER (not root), and the scan's
   files on the container's disk belong to it.

Everything is built in a storage of its own under a fresh folder of /var/tmp and removed at
the end, failed or not (containers, images, mounts, the folder); only the cached base stays.
The Debian packages (buildah, debootstrap) are installed by scripts/system-deps.sh when
missing. Progress goes to stderr; the result, one JSON object with the times in seconds, to
stdout (and ``--json FILE``). Exit status 0 when the scan is done with points and the server
runs as the image's user, 1 otherwise. ``make image`` runs it; tests/test_docker.py too.
"""
from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "docker" / "Dockerfile"

SUITE, VARIANT, INCLUDE = "bookworm", "minbase", "python3-venv"
MIRROR = os.environ.get("FLYSCAN_DEBIAN_MIRROR", "http://deb.debian.org/debian")
VENV = "/opt/venv"
BASE_PATH = f"{VENV}/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
#: What the base is made of: the cached tar's name carries its hash, so a change rebuilds it.
BASE_RECIPE = f"{SUITE} {VARIANT} {INCLUDE} {MIRROR} venv {VENV} no-apt-cache 1"
BASE_TAG, IMAGE_TAG = "localhost/flyscan-base:local", "localhost/flyscan:local"

#: Upper bounds for each step, far above what it takes on 2 busy cores, so a hung step ends.
DEBOOTSTRAP_TIMEOUT_S, BUILD_TIMEOUT_S, STEP_TIMEOUT_S = 900, 1200, 300
POLL_S = 0.5


class Failed(RuntimeError):
    """A step that did not do its job, with what it printed."""


def _stopped(signum, _frame):
    """SIGTERM (a test's timeout): fail where the run is, so that it cleans up; once only."""
    signal.signal(signum, signal.SIG_IGN)
    raise Failed(f"stopped by signal {signum}")


def log(message: str) -> None:
    print(f"build_local: {message}", file=sys.stderr, flush=True)


def run(argv, *, timeout=STEP_TIMEOUT_S, output: Path | None = None, **kwargs) -> str:
    """``argv`` run to its end; its stdout, or Failed with the tail of what it printed."""
    if output is None:
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, **kwargs)
        text = proc.stdout + proc.stderr
    else:
        with output.open("w") as out:
            proc = subprocess.run(argv, stdout=out, stderr=subprocess.STDOUT, text=True,
                                  timeout=timeout, **kwargs)
        text = output.read_text(errors="replace")
    if proc.returncode != 0:
        tail = "\n".join(text.splitlines()[-40:])
        raise Failed(f"{' '.join(map(str, argv[:6]))} ... exited {proc.returncode}:\n{tail}")
    return proc.stdout if output is None else text


def ensure_tools() -> None:
    if os.geteuid() != 0:
        raise Failed("needs root (debootstrap, and buildah's chroot isolation as root)")
    if shutil.which("buildah") and shutil.which("debootstrap"):
        return
    log("installing buildah and debootstrap (scripts/system-deps.sh docker)")
    run(["bash", str(ROOT / "scripts" / "system-deps.sh"), "docker"], timeout=900)
    missing = [t for t in ("buildah", "debootstrap") if not shutil.which(t)]
    if missing:
        raise Failed(f"{', '.join(missing)} not installed (apt-get install {' '.join(missing)})")


def free_ports(count: int) -> list[int]:
    """Ports free on the loopback now (the kernel's choice; held open together, so distinct)."""
    sockets = [socket.socket() for _ in range(count)]
    try:
        for s in sockets:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


#: The server is on the loopback: never through a proxy the environment may name.
_OPENER = urllib.request.build_opener(urllib.request.ProxyHandler({}))


def http(method: str, url: str, body: dict | None = None, timeout: float = 10.0):
    """(status, parsed JSON or raw bytes) of one request."""
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(url, data=data, method=method,
                                     headers={"Content-Type": "application/json"})
    with _OPENER.open(request, timeout=timeout) as response:
        raw = response.read()
        kind = response.headers.get("Content-Type", "")
        return response.status, (json.loads(raw) if "json" in kind else raw)


class Buildah:
    """buildah on a storage of its own (under ``work``), so that removing it removes all."""

    def __init__(self, work: Path):
        self.argv = ["buildah", "--root", str(work / "storage"), "--runroot",
                     str(work / "runroot"), "--storage-driver", "overlay"]

    def __call__(self, *args, **kwargs) -> str:
        return run([*self.argv, *args], **kwargs).strip()

    def remove_all(self) -> None:
        for args in (("rm", "--all"), ("rmi", "--all", "--force")):
            try:
                self(*args, timeout=120)
            except (Failed, subprocess.TimeoutExpired) as exc:
                log(f"cleanup: buildah {' '.join(args)}: {exc}")


def base_tar(work: Path, cache_dir: Path | None) -> tuple[Path, bool]:
    """The base's root file system as a tar: (path, whether it came from the cache)."""
    key = hashlib.sha256(BASE_RECIPE.encode()).hexdigest()[:12]
    day = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%d")
    name = f"{SUITE}-{VARIANT}-{INCLUDE}-{day}-{key}.tar"
    if cache_dir is not None and (cache_dir / name).is_file():
        return cache_dir / name, True
    rootfs = work / "rootfs"
    log(f"debootstrap {SUITE} ({VARIANT}, {INCLUDE}) from {MIRROR}")
    run(["debootstrap", f"--variant={VARIANT}", f"--include={INCLUDE}", SUITE, str(rootfs),
         MIRROR], timeout=DEBOOTSTRAP_TIMEOUT_S, output=work / "debootstrap.log")
    run(["chroot", str(rootfs), "python3", "-m", "venv", VENV])
    # As python:3.11-slim: no package cache, no package lists.
    for folder in ("var/cache/apt/archives", "var/lib/apt/lists"):
        for entry in (rootfs / folder).glob("*"):
            if entry.is_file():
                entry.unlink()
    target = (cache_dir or work) / name
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = target.with_name(f".{name}.{os.getpid()}")
    try:
        run(["tar", "--numeric-owner", "--one-file-system", "-C", str(rootfs), "-cf",
             str(partial), "."])
        partial.replace(target)                 # whole or absent, for a concurrent run
    finally:
        partial.unlink(missing_ok=True)
    if cache_dir is not None:
        for old in cache_dir.glob(f"{SUITE}-{VARIANT}-*.tar"):
            if old != target:
                old.unlink(missing_ok=True)
    run(["rm", "-rf", "--one-file-system", str(rootfs)])
    return target, False


def make_base(buildah: Buildah, work: Path, cache_dir: Path | None) -> bool:
    tar, cached = base_tar(work, cache_dir)
    log(f"base from {tar}{' (cached)' if cached else ''}")
    container = buildah("from", "scratch")
    mount = buildah("mount", container)
    run(["tar", "--numeric-owner", "-C", mount, "-xf", str(tar)])
    buildah("umount", container)
    buildah("config", "--env", f"PATH={BASE_PATH}", "--env", "LANG=C.UTF-8",
            "--cmd", "python3", container)
    buildah("commit", "--quiet", "--rm", "--format", "docker", container, BASE_TAG)
    return cached


def build_image(buildah: Buildah, work: Path) -> None:
    """docker/Dockerfile on the base; pip in the build sees the machine's CA bundle."""
    ca = Path(os.environ.get("PIP_CERT") or "/etc/ssl/certs/ca-certificates.crt")
    if not ca.is_file():
        raise Failed(f"no CA bundle at {ca} (set PIP_CERT to the machine's bundle)")
    pip = work / "pip"
    pip.mkdir()
    shutil.copyfile(ca, pip / "ca.crt")
    # /etc/xdg/pip/pip.conf is pip's site-wide configuration; mounted for the build only.
    (pip / "pip.conf").write_text("[global]\ncert = /etc/xdg/pip/ca.crt\n")
    log(f"buildah bud {DOCKERFILE.relative_to(ROOT)} (BASE_IMAGE={BASE_TAG})")
    buildah("bud", "--isolation", "chroot", "--network", "host", "--pull=never",
            "--layers=false", "--format", "docker", "--file", str(DOCKERFILE),
            "--build-arg", f"BASE_IMAGE={BASE_TAG}", "--volume", f"{pip}:/etc/xdg/pip:ro",
            "--tag", IMAGE_TAG, str(ROOT), timeout=BUILD_TIMEOUT_S, output=work / "build.log")


def image_config(buildah: Buildah) -> dict:
    return json.loads(buildah("inspect", "--type", "image", IMAGE_TAG))["OCIv1"]["config"]


def serve_argv(config: dict, rest_port: int, zmq_port: int) -> list[str]:
    """The image's ENTRYPOINT + CMD with its address moved to free loopback ports."""
    argv = [*(config.get("Entrypoint") or []), *(config.get("Cmd") or [])]
    if argv[:2] != ["flyscan", "serve"]:
        raise Failed(f"the image does not run flyscan serve: {argv}")
    for option, value in (("--host", "127.0.0.1"), ("--port", str(rest_port)),
                          ("--zmq", f"tcp://127.0.0.1:{zmq_port}")):
        if option not in argv:
            raise Failed(f"the image's command has no {option}: {argv}")
        argv[argv.index(option) + 1] = value
    return argv


def descendants(pid: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def uids(pid: int) -> tuple[str, set[int]]:
    """(command line, {real, effective, saved, filesystem uid}) of a process; ("", set()) for
    one that has gone."""
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        status = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError:
        return "", set()
    line = next(l for l in status if l.startswith("Uid:"))
    return cmdline.strip(), {int(u) for u in line.split()[1:]}


def wait_for(what: str, check, timeout: float, server: subprocess.Popen, serve_log: Path):
    """``check()`` polled until it returns something true; Failed if the server exits."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise Failed(f"the server exited {server.returncode} before {what}:\n"
                         + "\n".join(serve_log.read_text(errors="replace").splitlines()[-30:]))
        result = check()
        if result:
            return result
        time.sleep(POLL_S)
    raise Failed(f"no {what} after {timeout:.0f} s")


def health_ok(url: str) -> bool:
    try:
        status, body = http("GET", f"{url}/health", timeout=2)
    except (OSError, urllib.error.URLError):
        return False
    return status == 200 and body == {"status": "ok"}


def scan_finished(url: str, scan_id: str):
    _, info = http("GET", f"{url}/scans/{scan_id}")
    return info if info["state"] in ("done", "failed") else None


def stop(server: subprocess.Popen) -> None:
    """The server's process group (buildah run and everything under it) ended."""
    if server.poll() is not None:
        return
    for sig, grace in ((signal.SIGTERM, 20), (signal.SIGKILL, 10)):
        try:
            os.killpg(server.pid, sig)
        except ProcessLookupError:
            return
        try:
            server.wait(grace)
            return
        except subprocess.TimeoutExpired:
            continue


def unmount_under(work: Path) -> list[str]:
    """Unmount whatever is still mounted under ``work`` (deepest first); what remains."""
    def mounted():
        points = []
        for line in Path("/proc/self/mountinfo").read_text().splitlines():
            point = line.split()[4].replace("\\040", " ")
            if point == str(work) or point.startswith(f"{work}/"):
                points.append(point)
        return sorted(set(points), key=len, reverse=True)

    for point in mounted():
        subprocess.run(["umount", "--lazy", point], capture_output=True, timeout=60)
    return mounted()


def run_all(args, work: Path) -> dict:
    buildah = Buildah(work)
    # The machine's load when the run starts: the times below depend on it.
    result: dict = {"load_1min": round(os.getloadavg()[0], 1)}
    server = None
    t_start = time.monotonic()
    try:
        t0 = time.monotonic()
        result["base_cached"] = make_base(buildah, work, args.cache_dir)
        result["base_s"] = round(time.monotonic() - t0, 1)
        log(f"base in {result['base_s']} s")

        t0 = time.monotonic()
        build_image(buildah, work)
        result["image_s"] = round(time.monotonic() - t0, 1)
        config = image_config(buildah)
        user = config.get("User") or "root"
        result["image_user"] = user
        # What the run holds on disk at its largest: the storage with both images, the tar.
        result["disk_mb"] = int(run(["du", "-sxm", str(work)]).split()[0])
        log(f"image in {result['image_s']} s, USER {user}")

        rest_port, zmq_port = free_ports(2)
        url = f"http://127.0.0.1:{rest_port}"
        argv = serve_argv(config, rest_port, zmq_port)
        container = buildah("from", "--pull=never", IMAGE_TAG)
        serve_log = work / "serve.log"
        log(f"buildah run {' '.join(argv)}")
        t0 = time.monotonic()
        with serve_log.open("w") as out:
            server = subprocess.Popen(
                [*buildah.argv, "run", "--isolation", "chroot", "--network", "host", container,
                 "--", *argv], stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        wait_for("/health", lambda: health_ok(url), args.health_timeout_s, server, serve_log)
        result["health_s"] = round(time.monotonic() - t0, 1)
        log(f"/health after {result['health_s']} s")

        # The server's processes under buildah's own (buildah-chroot-runtime, root, outside).
        processes = [p for p in map(uids, descendants(server.pid)) if "flyscan serve" in p[0]]
        result["server_processes"] = [{"cmd": c[:120], "uids": sorted(u)} for c, u in processes]
        result["server_uids"] = sorted(set().union(*(u for _, u in processes)))

        t0 = time.monotonic()
        status, armed = http("POST", f"{url}/scans", {})
        if status != 202:
            raise Failed(f"POST /scans answered {status}: {armed}")
        scan_id = armed["scan_id"]
        info = wait_for(f"scan {scan_id} done", lambda: scan_finished(url, scan_id),
                        args.scan_timeout_s, server, serve_log)
        result["scan_s"] = round(time.monotonic() - t0, 1)
        result.update(scan_state=info["state"], scan_reason=info.get("reason"),
                      points=info.get("points") or 0, frames=info.get("frames"))
        _, ply = http("GET", f"{url}/scans/{scan_id}/cloud.ply")
        header = ply[:ply.find(b"end_header")].decode(errors="replace").splitlines()
        result["cloud_vertices"] = next((int(l.split()[2]) for l in header
                                         if l.startswith("element vertex")), None)
        # The image's VOLUME /data is the container's own volume: look from inside.
        owner = buildah("run", "--isolation", "chroot", container, "--", "stat", "-c", "%u",
                        f"/data/scans/{scan_id}/cloud.ply")
        result["scan_file_uid"] = int(owner)
        log(f"scan {info['state']} in {result['scan_s']} s, {result['points']} points")
    finally:
        if server is not None:
            stop(server)
        buildah.remove_all()
        result["total_s"] = round(time.monotonic() - t_start, 1)
    return result


def verdict(result: dict) -> list[str]:
    """What is wrong with a run's result; empty when the image did its job."""
    problems = []
    if result.get("scan_state") != "done" or result.get("points", 0) <= 0:
        problems.append(f"scan {result.get('scan_state')} ({result.get('scan_reason')}) "
                        f"with {result.get('points')} points")
    if result.get("cloud_vertices") != result.get("points"):
        problems.append(f"cloud.ply has {result.get('cloud_vertices')} vertices, the scan "
                        f"{result.get('points')} points")
    user = str(result.get("image_user", "root")).split(":")[0]
    if not user.isdigit() or int(user) == 0:
        problems.append(f"the image's USER is {user!r}, not an unprivileged numeric uid")
    elif not result.get("server_processes") or result.get("server_uids") != [int(user)]:
        problems.append(f"the server runs as uids {result.get('server_uids')}, not {user}")
    elif result.get("scan_file_uid") != int(user):
        problems.append(f"the scan's files belong to uid {result.get('scan_file_uid')}")
    return problems


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cache-dir", type=Path, default=Path("/var/cache/flyscan/docker-base"),
                        help="where the base's root file system is kept for the day "
                             "(default %(default)s)")
    parser.add_argument("--no-cache", dest="cache_dir", action="store_const", const=None,
                        help="debootstrap the base afresh and keep nothing")
    parser.add_argument("--health-timeout-s", type=float, default=600.0,
                        help="how long the server may take to answer /health (default 600: "
                             "the first start compiles the numba kernels)")
    parser.add_argument("--scan-timeout-s", type=float, default=120.0,
                        help="how long an armed scan may take to be done (default 120)")
    parser.add_argument("--json", type=Path, help="also write the result to this file")
    args = parser.parse_args(argv)

    signal.signal(signal.SIGTERM, _stopped)
    try:
        ensure_tools()
    except Failed as exc:
        log(str(exc))
        return 1
    work = Path(tempfile.mkdtemp(prefix="flyscan-image-", dir="/var/tmp"))
    result, error = {}, None
    try:
        result = run_all(args, work)
    except (Failed, subprocess.TimeoutExpired, OSError, KeyError, ValueError) as exc:
        error = f"{type(exc).__name__}: {exc}"
    finally:
        remaining = unmount_under(work)
        if remaining:
            log(f"cleanup: still mounted, {work} left in place: {remaining}")
        else:
            subprocess.run(["rm", "-rf", "--one-file-system", str(work)], timeout=300)
    result["cleaned"] = not remaining and not work.exists()
    problems = ([error] if error else verdict(result)) + ([] if result["cleaned"] else
                                                          [f"{work} not removed"])
    result["problems"] = problems
    text = json.dumps(result, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    for problem in problems:
        log(f"FAILED: {problem}")
    if not problems:
        log(f"ok: base {result['base_s']} s, image {result['image_s']} s, /health after "
            f"{result['health_s']} s, scan {result['scan_s']} s ({result['points']} points), "
            f"server as uid {result['server_uids']}")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
