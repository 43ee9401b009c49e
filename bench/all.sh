#!/usr/bin/env bash
# Run every benchmark in bench/ (each bench/*.py, found at run time) and print one table of their
# JSON result lines (the last line each prints; see bench/README.md).
#
#   bench/all.sh [--quick] [--python PYTHON] [--timeout SECONDS] [--skip NAME=REASON]... [--log-dir DIR]
#
# A bench is skipped, with its reason in the table, when named by --skip or when its file holds a
# line `# all.sh: skip REASON` (for a bench that cannot run here, e.g. one that needs a GPU). The
# python defaults to $PYTHON, else `python`. Each bench runs under `nice -n 10` with a time limit
# (default 600 s); its full output is kept in the log directory (default: a temporary one).
set -uo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
python="${PYTHON:-python}"
quick=()
limit=600
logs=""
declare -A skip=()
while (($#)); do
    case "$1" in
        --quick) quick=(--quick) ;;
        --python) python="$2"; shift ;;
        --timeout) limit="$2"; shift ;;
        --log-dir) logs="$2"; shift ;;
        --skip) skip["${2%%=*}"]="${2#*=}"; shift ;;
        -h | --help) sed -n '2,11p' "$0"; exit 0 ;;
        *) echo "all.sh: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done
logs="${logs:-$(mktemp -d -t shiftkit-bench-XXXXXX)}"
mkdir -p "$logs"
results="$logs/results.jsonl"
: >"$results"
export MUJOCO_GL="${MUJOCO_GL:-egl}" HF_HUB_OFFLINE="${HF_HUB_OFFLINE:-1}"

for file in "$here"/*.py; do
    name="$(basename "$file" .py)"
    [[ "$name" == _* ]] && continue  # a helper the benches share, not a bench
    reason="${skip[$name]:-$(sed -n 's/^# all\.sh: skip //p' "$file" | head -n 1)}"
    if [[ -n "$reason" ]]; then
        "$python" -c 'import json, sys; print(json.dumps({"bench": sys.argv[1], "skipped": sys.argv[2]}))' \
            "$name" "$reason" >>"$results"
        echo "skip $name: $reason" >&2
        continue
    fi
    echo "run  $name ${quick[*]}" >&2
    start=$EPOCHREALTIME
    nice -n 10 timeout "$limit" "$python" "$file" "${quick[@]}" >"$logs/$name.log" 2>&1
    rc=$?
    "$python" - "$name" "$rc" "$start" "$EPOCHREALTIME" "$logs/$name.log" >>"$results" <<'EOF'
import json, sys
name, rc, log = sys.argv[1], int(sys.argv[2]), sys.argv[5]
seconds = float(sys.argv[4]) - float(sys.argv[3])
lines = [l for l in open(log, errors="replace").read().splitlines() if l.strip()]
try:
    result = json.loads(lines[-1])
    assert isinstance(result, dict) and rc == 0
except Exception:
    why = "timed out" if rc == 124 else f"exit {rc}, no JSON last line"
    result = {"bench": name, "error": f"{why} (see {log})"}
print(json.dumps({**result, "wall_s": round(seconds, 1)}))
EOF
done

"$python" - "$results" "$(uptime)" <<'EOF'
import json, sys

def fmt(x):
    return f"{x:.4g}" if isinstance(x, float) else str(x)

print(f"\n{sys.argv[2].strip()}\n")
print("| bench | metric | value | goal | met | wall s |")
print("|---|---|---|---|---|---|")
for line in open(sys.argv[1]):
    r = json.loads(line)
    if "skipped" in r or "error" in r:
        print(f"| {r['bench']} | {'skipped: ' + r['skipped'] if 'skipped' in r else 'FAILED: ' + r['error']} | | | | {r.get('wall_s', '')} |")
        continue
    goal, value = r.get("goal"), r.get("value")
    met = "" if goal is None or value is None else ("yes" if (value >= goal if r.get("higher_is_better", True) else value <= goal) else "no")
    print(f"| {r['bench']} | {r.get('metric', '')} | {fmt(value)} | {fmt(goal)} | {met} | {r['wall_s']} |")
print(f"\nJSON lines: {sys.argv[1]}")
EOF
