#!/usr/bin/env bash
# Create (if missing) the project's virtual environment and install this checkout into it.
# The heavy dependencies (torch, lerobot, ray: ~8 GB) live in a venv kept outside the clone,
# keyed by a hash of the dependency pins in pyproject.toml, so a new clone with the same pins reuses
# it while a change of pins or a fresh machine gets a correct new one (other edits, such as a new
# subpackage, only refresh the editable install). Prints the venv path on stdout.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
python="${PYTHON:-python3.11}"
command -v "$python" >/dev/null || python=python3
key="$("$python" - "$here/pyproject.toml" <<'PY'
import hashlib, json, sys, tomllib
project = tomllib.load(open(sys.argv[1], "rb"))["project"]
pins = {k: project.get(k) for k in ("requires-python", "dependencies", "optional-dependencies")}
print(hashlib.sha256(json.dumps(pins, sort_keys=True).encode()).hexdigest()[:16])
PY
)"
venv="${SHIFTKIT_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/shiftkit/venv-$key}"
if [ ! -f "$venv/.complete" ]; then
    echo "shiftkit: creating environment $venv (first run: ~3 min, ~8 GB)" >&2
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
