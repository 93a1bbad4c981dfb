#!/usr/bin/env bash
# The long reliability suite before a deployment: kill storm, power-cut loop on the modem
# leg (fresh outboxes against a surface that stays up), socket fuzzer, log flood and power
# cuts of whole pipelines with the /dev/shm check, for DURATION seconds of attack in all
# (start-up and the checks after each attack come on top); then, at their own length,
# forged results, the supervisor's channel, modem replays (one frame over the simulated
# link; four frames for 90 s through the schedule), viewer abuse (forged Hosts, slow
# clients), memory under hostile subscriptions and hellos, and a detector flooding 1,000
# boxes a pair beside VO for 60 s. The summary adds up
# what was lost, written twice or forged, and the largest memory growth per node. They are the tests of
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
# An absolute path whether OUT_DIR was given relative or absolute ("$PWD/$REPORT" made
# /repo//abs/dir/chaos.jsonl of an absolute one, and every test failed writing its figures).
export TRAPFLOW_CHAOS_REPORT="$(cd "$OUT" && pwd)/chaos.jsonl"
export TRAPFLOW_CHAOS_STORM_S=$(( DURATION * 45 / 100 ))
export TRAPFLOW_CHAOS_FUZZ_S=$(( DURATION * 25 / 100 ))
export TRAPFLOW_CHAOS_POWERCUTS=$(( DURATION * 15 / 150 > 8 ? DURATION * 15 / 150 : 8 ))
export TRAPFLOW_CHAOS_CUTS=$(( DURATION * 15 / 800 > 3 ? DURATION * 15 / 800 : 3 ))
export TRAPFLOW_CHAOS_FLOOD=$(( DURATION * 200 > 10000 ? DURATION * 200 : 10000 ))
export TRAPFLOW_CHAOS_BOX_FLOOD_S=60

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
  tests/reliability/test_hygiene_shm.py \
  tests/reliability/test_modem_fresh_outbox.py \
  "tests/reliability/test_forge.py::test_forged_answers_on_the_workers_socket_and_link_are_never_written" \
  "tests/reliability/test_forge.py::test_a_worker_cannot_attach_a_result_for_another_pair_or_pool" \
  tests/reliability/test_supervisor_channel.py \
  tests/reliability/test_modem_replay_budget.py \
  "tests/unit/test_modem_schedule.py::test_replayed_commands_leave_data_flowing_budget_or_not" \
  tests/reliability/test_box_flood.py \
  tests/reliability/test_modem_session_correction.py \
  tests/reliability/test_viewer_hosts.py \
  tests/reliability/test_viewer_slow_clients.py \
  tests/reliability/test_forge_subscriptions.py \
  tests/reliability/test_remote_table.py
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


def total(key: str) -> int:
    """A figure summed over every row that has it (a dict per pool summed too)."""
    out = 0
    for r in rows:
        v = r.get(key, 0)
        out += sum(v.values()) if isinstance(v, dict) else int(v)
    return out


def unaccounted(r: dict) -> int:
    """Results that should exist and do not. The kill storm's `lost` are pairs a killed
    worker held (the ledger counts them, by design); its losses are the ledger's mismatch."""
    v = r.get("ledger_mismatch", r.get("lost", 0))
    return sum(map(abs, v.values())) if isinstance(v, dict) else abs(int(v))


in_flight = sum(sum(r["lost"].values()) for r in rows if "ledger_mismatch" in r)
growth: dict[str, float] = {}
for r in rows:
    for node, mb in (r.get("growth_mb") or {}).items():
        growth[node] = max(growth.get(node, mb), mb)
lines += ["", "## Summary", "",
          f"- lost: {sum(unaccounted(r) for r in rows)} (results acknowledged or processed "
          f"but not delivered; pairs held by a killed worker, counted in the ledger: "
          f"{in_flight})", f"- duplicates: {total('duplicates')}",
          f"- forged lines written: {total('forged_written')}",
          "- memory growth per node (largest, MB): "
          + (", ".join(f"{n} {mb:+.2f}" for n, mb in sorted(growth.items())) or "not measured")]
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
