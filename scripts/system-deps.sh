#!/usr/bin/env bash
# Debian packages flyscan needs beside its Python packages; installs the missing ones.
#   libgl1: pymeshlab (the simulator's mesh simplification) links against libGL.
#   chromium: the status page's browser test (playwright drives Debian's chromium; it cannot
#     download a browser of its own here).
#   libusb-1.0-0 (with the argument "bench"): Open3D, the benchmarks' yardstick, links to it.
#   buildah, debootstrap (with the argument "docker"): docker/build_local.py builds and runs the
#     Docker image without a Docker engine or a registry (docs/docker.md).
set -euo pipefail
packages=(libgl1 chromium)
case "${1:-}" in
    bench) packages+=(libusb-1.0-0) ;;
    docker) packages+=(buildah debootstrap) ;;
esac
missing=()
for pkg in "${packages[@]}"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
[ ${#missing[@]} -eq 0 ] && exit 0
if ! command -v apt-get >/dev/null; then
    echo "system-deps: not a Debian system; install the equivalent of: ${missing[*]}" >&2
    exit 0
fi
run=()
if [ "$(id -u)" -ne 0 ]; then
    if ! command -v sudo >/dev/null; then
        echo "system-deps: missing ${missing[*]}; install them as root (apt-get install ${missing[*]})" >&2
        exit 0
    fi
    run=(sudo)
fi
echo "system-deps: installing ${missing[*]}" >&2
# Another apt-get (another user's install) may hold dpkg's lock: wait for it rather than fail.
"${run[@]}" apt-get update -qq -o DPkg::Lock::Timeout=300
DEBIAN_FRONTEND=noninteractive "${run[@]}" apt-get install -y -qq --no-install-recommends \
    -o DPkg::Lock::Timeout=300 "${missing[@]}"
