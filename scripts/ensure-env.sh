#!/usr/bin/env bash
# Create (if missing) this checkout's Python environment and print its path on stdout.
#
# Two layers, so that clones never run each other's code and still share the heavy part:
# * the dependencies (torch, lerobot, ray, ...: ~6 GB) live in one venv outside the clone, keyed by a
#   hash of the dependency pins in pyproject.toml (`deps-<hash>`, without shiftkit itself), shared by
#   every clone with the same pins; a change of pins or a fresh machine gets a correct new one;
# * each checkout has its own small venv, `.venv/` in the clone, that sees the dependency venv
#   through a `.pth` file and holds the editable install of this checkout only (and copies of the
#   dependencies' console scripts, such as `lerobot-train` and `ray`, bound to this venv's Python).
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
# The pins' hash and the requirement lines (dependencies + the dev extra) from pyproject.toml.
pins="$("$python" - "$here/pyproject.toml" <<'PY'
import hashlib, json, sys, tomllib
project = tomllib.load(open(sys.argv[1], "rb"))["project"]
pins = {k: project.get(k) for k in ("requires-python", "dependencies", "optional-dependencies")}
print(hashlib.sha256(json.dumps(pins, sort_keys=True).encode()).hexdigest()[:16])
for requirement in project["dependencies"] + project["optional-dependencies"]["dev"]:
    print(requirement)
PY
)"
key="$(head -n 1 <<<"$pins")"
deps="${SHIFTKIT_DEPS_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/shiftkit/deps-$key}"
venv="${SHIFTKIT_VENV:-$here/.venv}"

run_logged() {  # run a command quietly; on failure show the end of its output and say what failed
    local what="$1"; shift
    local log; log="$(mktemp)"
    if ! "$@" >"$log" 2>&1; then
        tail -n 40 "$log" >&2; rm -f "$log"
        echo "shiftkit: $what failed (see above)" >&2; exit 1
    fi
    rm -f "$log"
}

if [ ! -f "$deps/.complete" ]; then
    echo "shiftkit: creating the dependency environment $deps (first run: ~4 min, ~6 GB)" >&2
    rm -rf "$deps"
    requirements="$(mktemp)"; tail -n +2 <<<"$pins" >"$requirements"
    run_logged "creating $deps" bash -c '"$1" -m venv "$2" && "$2/bin/python" -m pip install --upgrade pip setuptools wheel && "$2/bin/python" -m pip install -r "$3"' _ "$python" "$deps" "$requirements"
    rm -f "$requirements"
    touch "$deps/.complete"
fi

# This checkout's venv: recreated when it is missing or was made over another dependency venv.
site="$("$deps/bin/python" -c 'import sysconfig; print(sysconfig.get_path("purelib"))')"
if [ ! -x "$venv/bin/python" ] || [ "$(cat "$venv/.shiftkit-deps" 2>/dev/null)" != "$deps" ]; then
    rm -rf "$venv"
    run_logged "creating $venv" "$deps/bin/python" -m venv --without-pip "$venv"
    own_site="$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_path("purelib"))')"
    # addsitedir (not a bare path line) also runs the dependency venv's own .pth files.
    printf 'import site; site.addsitedir(%s)\n' "$("$python" -c 'import sys; print(repr(sys.argv[1]))' "$site")" \
        >"$own_site/_shiftkit_dependencies.pth"
    # The dependencies' console scripts, bound to this venv's Python (tests call lerobot-train, ray);
    # their binaries (ruff) linked.
    for script in "$deps"/bin/*; do
        name="$(basename "$script")"
        [ -e "$venv/bin/$name" ] || [ ! -f "$script" ] || [ ! -x "$script" ] && continue
        if head -c 200 "$script" | head -n 1 | grep -q "^#!$deps/bin/python"; then
            { echo "#!$venv/bin/python"; tail -n +2 "$script"; } >"$venv/bin/$name"
            chmod +x "$venv/bin/$name"
        else
            ln -s "$script" "$venv/bin/$name"
        fi
    done
    echo "$deps" >"$venv/.shiftkit-deps"
    rm -f "$venv/.shiftkit-install"
fi
# An older install's `shiftkit.egg-info` in the checkout shadows the venv's package metadata for any
# command run from the checkout (its entry points, e.g. the stage plug-ins, go stale): never keep one.
rm -rf "$here/shiftkit.egg-info"
# The editable install of this checkout, redone when the packaging or the set of packages changed.
stamp="$(cd "$here" && { cat pyproject.toml setup.py; find . -path ./.venv -prune -o -path ./.git -prune -o -name __init__.py -print | sort; } | sha256sum | cut -c1-16)"
if [ "$(cat "$venv/.shiftkit-install" 2>/dev/null)" != "$stamp" ]; then
    run_logged "installing $here into $venv" "$venv/bin/python" -m pip install -q --no-deps --no-build-isolation -e "$here"
    echo "$stamp" >"$venv/.shiftkit-install"
fi
echo "$venv"
