#!/usr/bin/env bash
# Create (if missing) the project's virtual environment and install this checkout into it.
# The heavy dependencies (torch, lerobot, ray: ~6 GB) live in a venv kept outside the clone,
# keyed by a hash of the dependency pins in pyproject.toml, so a new clone with the same pins reuses
# it while a change of pins or a fresh machine gets a correct new one (other edits, such as a new
# subpackage, only refresh the editable install). Prints the venv path on stdout.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# lerobot 0.6 needs Python >= 3.12: $PYTHON, else python3.12 / python3.13 / python3 on PATH, else pyenv's.
is_py312() { "$1" -c 'import sys; sys.exit(not (3, 12) <= sys.version_info[:2] < (3, 14))' 2>/dev/null; }
python=""
for candidate in ${PYTHON:-} python3.12 python3.13 python3 \
        "${PYENV_ROOT:-$HOME/.pyenv}"/versions/3.12*/bin/python3 "${PYENV_ROOT:-$HOME/.pyenv}"/versions/3.13*/bin/python3; do
    if command -v "$candidate" >/dev/null && is_py312 "$candidate"; then python="$candidate"; break; fi
done
if [ -z "$python" ]; then
    echo "shiftkit: no Python 3.12 or 3.13 found (tried \$PYTHON, python3.12, python3.13, python3, pyenv): install one, e.g. 'pyenv install 3.12', or set PYTHON=/path/to/python3.12" >&2
    exit 1
fi
key="$("$python" - "$here/pyproject.toml" <<'PY'
import hashlib, json, sys, tomllib
project = tomllib.load(open(sys.argv[1], "rb"))["project"]
pins = {k: project.get(k) for k in ("requires-python", "dependencies", "optional-dependencies")}
print(hashlib.sha256(json.dumps(pins, sort_keys=True).encode()).hexdigest()[:16])
PY
)"
venv="${SHIFTKIT_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/shiftkit/venv-$key}"
if [ ! -f "$venv/.complete" ]; then
    echo "shiftkit: creating environment $venv (first run: ~4 min, ~6 GB)" >&2
    rm -rf "$venv"
    log="$(mktemp)"
    if ! { "$python" -m venv "$venv" &&
           "$venv/bin/python" -m pip install --upgrade pip setuptools wheel &&
           "$venv/bin/python" -m pip install -e "$here[dev]"; } >"$log" 2>&1; then
        tail -n 40 "$log" >&2; rm -f "$log"
        echo "shiftkit: creating $venv failed (see above)" >&2; exit 1
    fi
    rm -f "$log"
    touch "$venv/.complete"
fi
# Always (re)point the editable install at this checkout: several clones may share one venv.
log="$(mktemp)"
if ! "$venv/bin/python" -m pip install -q --no-deps --no-build-isolation -e "$here" >"$log" 2>&1; then
    cat "$log" >&2; rm -f "$log"; exit 1
fi
rm -f "$log"
echo "$venv"
