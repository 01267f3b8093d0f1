#!/usr/bin/env bash
# Sets robot_change up on Debian bookworm (as root): the system libraries it needs
# (libopenni2-0, python3-venv), a virtual environment in .venv, and the package itself
# (editable) with the extras named in the first argument.
#   ./setup.sh            -> extras "viz"          (to run robot-change and draw pictures)
#   ./setup.sh test,viz   -> plus the test tools   (to run the test suite; the `test` extra
#                            also brings Debian's mosquitto broker and openssl: the fleet
#                            tests start brokers of their own on free loopback ports)
# Safe to run again: it only installs what is missing.  PYTHON=... picks the interpreter.
set -euo pipefail
cd "$(dirname "$0")"
extras="${1:-viz}"

packages=(libopenni2-0 python3-venv)
case ",$extras," in *,test,*) packages+=(mosquitto openssl) ;; esac
missing=()
for package in "${packages[@]}"; do
    dpkg -s "$package" >/dev/null 2>&1 || missing+=("$package")
done
if [ "${#missing[@]}" -gt 0 ]; then
    if [ "$(id -u)" -ne 0 ]; then
        echo "setup.sh: run as root, or install these Debian packages first: ${missing[*]}" >&2
        exit 1
    fi
    echo "setup.sh: installing ${missing[*]}" >&2
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
fi

python="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
    echo "setup.sh: creating .venv with $("$python" --version 2>&1)" >&2
    "$python" -m venv .venv
fi
echo "setup.sh: installing robot-change[$extras] into .venv" >&2
.venv/bin/python -m pip install --quiet --disable-pip-version-check -e ".[$extras]"
# compile the numba kernels now (cached beside the package), so that the first run does not
echo "setup.sh: compiling the numba kernels (once; about 30 s on a 2-core machine)" >&2
.venv/bin/robot-change warm-up
