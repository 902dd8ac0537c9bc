#!/usr/bin/env bash
# Installs image2sim's Python packages into the virtual environment VENV, torch first: `make install` calls it.
#
# Usage: .ci/python-packages.sh VENV
#
# uv installs the wheels in parallel and compiles their bytecode on every core: on a clean clone on a 2-core machine
# (2026-11-27) 1 min 2 s, against 2 min 28 s to 2 min 45 s with pip, which extracts and compiles on one core.
# Bytecode is compiled at install time on purpose: where PYTHONDONTWRITEBYTECODE is set (as on that machine) Python
# never caches what it compiles on import, and every process of the test run would compile torch again (pytest took
# 2 min longer).
# Where uv cannot be installed or fails, pip installs everything, as before.
set -euo pipefail
venv=$1
py=$venv/bin/python
uv=$venv/bin/uv
uv_version=0.13.9

# pip's local wheel folders (this machine keeps the CPU build of torch in one) are passed on to uv, which does not
# read pip's configuration. Without any, torch comes from pip, which reads its own.
links=()
for link in ${PIP_FIND_LINKS:-} $("$py" -m pip config get global.find-links 2>/dev/null || true); do
  links+=(--find-links "$link")
done

"$py" -m pip install --quiet "uv==$uv_version" 2>/dev/null || echo "python-packages: uv unavailable; pip installs" >&2

with_uv() {
  [[ -x $uv ]] && "$uv" pip install --quiet --python "$py" --compile-bytecode ${links[@]+"${links[@]}"} "$@"
}

# torch first, pinned: the CPU build on this machine; a plain `torch` would pull a multi-GB CUDA build.
if ! "$py" -c "import sys, torch; sys.exit(torch.__version__.split('+')[0] != '2.13.0')" 2>/dev/null; then
  if ! { ((${#links[@]})) && with_uv torch==2.13.0; }; then
    "$py" -m pip install --quiet torch==2.13.0
  fi
fi
# constraints.txt: the versions the tests and README figures were measured with (newer releases drift).
if ! with_uv -c constraints.txt -e '.[test]'; then
  "$py" -m pip install --quiet --upgrade pip
  "$py" -m pip install --quiet -c constraints.txt -e '.[test]'
fi
