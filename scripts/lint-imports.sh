#!/usr/bin/env bash
# Check the dependency contracts (pyproject.toml [tool.importlinter]) with import-linter.
# The top-level folders are mapped into `shiftkit.*` by setuptools package-dir, which import-linter's
# file walker cannot see through an editable install; it reads a copy laid out as the installed
# package instead (sources only, deleted afterwards).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$1"
tree="$(mktemp -d)"
trap 'rm -rf "$tree"' EXIT
mkdir "$tree/shiftkit"
touch "$tree/shiftkit/__init__.py"
for package in datasets pipelines transforms policies envs cards app; do
    (cd "$here" && find "$package" -name '*.py' -not -path '*/__pycache__/*' -exec cp --parents {} "$tree/shiftkit/" \;)
done
cd "$here" && PYTHONPATH="$tree" "$venv/bin/lint-imports" --no-cache
