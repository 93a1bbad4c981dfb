#!/usr/bin/env bash
# The long reliability suite before a deployment: kill storm, power-cut loop on the modem
# leg (fresh outboxes against a surface that stays up), socket fuzzer, log flood and power
# cuts of whole pipelines with the /dev/shm check, for DURATION seconds of attack in all
# (start-up and the checks after each attack come on top). They are the tests of
# tests/reliability, made longer through TRAPFLOW_CHAOS_* variables; each reports its
# figures, and the report goes to OUT_DIR/chaos.md (with chaos.jsonl, the raw figures).
# Usage: scripts/chaos.sh DURATION [OUT_DIR]   (set PYTHON to choose the interpreter)
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ $# -lt 1 || ! ${1} =~ ^[0-9]+$ || ${1} -lt 60 ]]; then
  echo "usage: scripts/chaos.sh DURATION [OUT_DIR]: expected DURATION in whole seconds," \
       "at least 60 (600 before a deployment), got '${1:-}'" >&2
  exit 2
fi
DURATION=$1
OUT=${2:-bench-results}
PY=${PYTHON:-python}
mkdir -p "$OUT"
REPORT="$OUT/chaos.jsonl"
: > "$REPORT"

# The attack time, shared out: storm 45 %, fuzzer 25 %, modem power cuts 15 % (about
# 1.5 s each), pipeline power cuts 15 % (about 8 s each); the flood grows with it too.
export TRAPFLOW_CHAOS_REPORT="$PWD/$REPORT"
export TRAPFLOW_CHAOS_STORM_S=$(( DURATION * 45 / 100 ))
export TRAPFLOW_CHAOS_FUZZ_S=$(( DURATION * 25 / 100 ))
export TRAPFLOW_CHAOS_POWERCUTS=$(( DURATION * 15 / 150 > 8 ? DURATION * 15 / 150 : 8 ))
export TRAPFLOW_CHAOS_CUTS=$(( DURATION * 15 / 800 > 3 ? DURATION * 15 / 800 : 3 ))
export TRAPFLOW_CHAOS_FLOOD=$(( DURATION * 200 > 10000 ? DURATION * 200 : 10000 ))

echo "[chaos] ${DURATION} s: storm ${TRAPFLOW_CHAOS_STORM_S} s, fuzzer" \
     "${TRAPFLOW_CHAOS_FUZZ_S} s, ${TRAPFLOW_CHAOS_POWERCUTS} modem power cuts," \
     "${TRAPFLOW_CHAOS_CUTS} pipeline power cuts, ${TRAPFLOW_CHAOS_FLOOD} flood messages" >&2
start=$(date +%s)
set +e
"$PY" -m pytest -q -p no:cacheprovider --junitxml="$OUT/chaos-junit.xml" \
  tests/reliability/test_kill_storm.py \
  tests/reliability/test_modem_powercut_sessions.py \
  tests/reliability/test_fuzz_sockets.py \
  "tests/reliability/test_forge.py::test_heartbeat_flood_writes_few_lines_and_wire_names_cannot_forge_a_line" \
  tests/reliability/test_hygiene_shm.py
status=$?
set -e
wall=$(( $(date +%s) - start ))

"$PY" - "$OUT" "$DURATION" "$wall" "$status" <<'EOF'
import json
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

out, duration, wall, status = Path(sys.argv[1]), sys.argv[2], sys.argv[3], int(sys.argv[4])
rows = [json.loads(x) for x in (out / "chaos.jsonl").read_text().splitlines() if x.strip()]
cases = []
for case in ET.parse(out / "chaos-junit.xml").getroot().iter("testcase"):
    failed = case.find("failure") is not None or case.find("error") is not None
    skipped = case.find("skipped") is not None
    cases.append((case.get("name"), "failed" if failed else "skipped" if skipped else "passed",
                  float(case.get("time", 0))))
lines = [f"# trapflow chaos run, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
         "", f"`scripts/chaos.sh {duration}`: {wall} s of wall time, pytest exit {status} "
         f"({'all passed' if status == 0 else 'SOME FAILED'}).", "",
         "| test | outcome | s |", "|---|---|---|"]
lines += [f"| {n} | {o} | {t:.0f} |" for n, o, t in cases]
lines += ["", "## Figures", ""]
for r in rows:
    name = r.pop("test")
    r.pop("at", None)
    lines.append(f"- **{name}**: " + ", ".join(f"{k} {v}" for k, v in r.items()))
lines.append("")
(out / "chaos.md").write_text("\n".join(lines))
print("\n".join(lines))
EOF
exit $status
