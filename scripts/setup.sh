#!/usr/bin/env bash
# Create the project-local virtual environment .venv with everything gtgen needs.
# Idempotent: re-running only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

# open3d's CPU wheel links against libusb-1.0 from the system.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    echo "setup: installing Debian's libusb-1.0-0 (needed by open3d)"
    apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    echo "setup: open3d needs the system library libusb-1.0; install it first, e.g. 'sudo apt-get install -y libusb-1.0-0'" >&2
    exit 1
  fi
fi

if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.gtgen-installed
# PyPI over a flaky link: pip retries each connection and resumes a cut download, and the
# whole install is tried three times before the script gives up (it installs only what is missing).
export PIP_RETRIES=10 PIP_TIMEOUT=60
pip_install() {
  local n
  for n in 1 2 3; do
    .venv/bin/python -m pip install -q "$@" && return 0
    echo "setup: pip install $* failed (try $n of 3)" >&2
    sleep 5
  done
  return 1
}
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  pip_install --upgrade pip
  export PIP_RESUME_RETRIES=20
  # The CPU build of torch; a GPU user installs their CUDA build into .venv before this
  # script (see docs/getting-started.md), and this line then keeps it because it is already satisfied.
  .venv/bin/python -c "import torch" 2>/dev/null || pip_install "torch==2.13.0"
  pip_install -e ".[dev]"
  touch "$stamp"
fi
