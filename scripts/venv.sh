#!/usr/bin/env bash
# Creates (or reuses) .venv with a CPU build of torch and this package installed in editable mode.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null 2>&1 || PY=python3
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
pip_install() {
  local log
  log=$(mktemp)
  if ! .venv/bin/python -m pip install -q --disable-pip-version-check "$@" >"$log" 2>&1; then
    cat "$log" >&2
    rm -f "$log"
    return 1
  fi
  grep -v "^WARNING: Location" "$log" || true
  rm -f "$log"
}
stamp=.venv/.torchrl_mbmf-installed
want=$(cat pyproject.toml scripts/venv.sh | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  # The CPU build of torch first: an unpinned torch would pull a multi-GB CUDA build.
  pip_install "torch==2.13.0"
  pip_install -e ".[test]"
  .venv/bin/python -c "import torch, torchrl, tensordict, gymnasium, mujoco, hydra"
  echo "$want" >"$stamp"
fi
