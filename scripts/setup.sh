#!/usr/bin/env bash
# Installs hairwarp and what it needs on a fresh machine. torch goes first, pinned to the CPU
# build this machine holds, so the library's torch range pulls no CUDA packages.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m pip install -q --disable-pip-version-check "torch==2.13.0" || python3 -m pip install -q "torch>=2.4,<3"
python3 -m pip install -q --disable-pip-version-check -e ".[test]"
