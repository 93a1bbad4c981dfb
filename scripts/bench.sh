#!/usr/bin/env bash
# Benchmarks of trapflow on this machine; numbers go to bench-results/ (JSON per part and
# bench.md with everything). Speed is measured here, never asserted in tests.
# Usage: scripts/bench.sh [OUT_DIR]   (set PYTHON to choose the interpreter)
set -euo pipefail
usage() {
  cat <<'USAGE'
Usage: scripts/bench.sh [OUT_DIR]
Runs trapflow's benchmarks on this machine (transport, shared memory, synthetic source,
algorithms, batch processing, live viewer, modem link) and writes OUT_DIR/*.json and
OUT_DIR/bench.md (OUT_DIR: bench-results). Set PYTHON to choose the interpreter.
Run time: several minutes, and it loads every core: the live viewer part alone runs 30 s
against a running pipeline and the transport part repeats each path 5 times. Run it on an
otherwise idle machine; speed is measured here, never asserted in tests.
USAGE
}
case "${1:-}" in
  -h|--help) usage; exit 0 ;;
  -*) echo "scripts/bench.sh: unknown option $1 (expected OUT_DIR or --help)" >&2; usage >&2; exit 2 ;;
esac
cd "$(dirname "$0")/.."
OUT=${1:-bench-results}
PY=${PYTHON:-python}
mkdir -p "$OUT"
echo "[bench] transport (broker path vs raw pyzmq)" >&2
"$PY" scripts/bench_transport.py --out "$OUT" > /dev/null
echo "[bench] remote pools (tcp with CURVE vs raw pyzmq over tcp)" >&2
"$PY" scripts/bench_remote.py --out "$OUT" > /dev/null
for part in bench_shm bench_synth; do
  if [ -f "scripts/$part.py" ]; then
    echo "[bench] $part" >&2
    "$PY" "scripts/$part.py" --out "$OUT" > /dev/null
  fi
done
echo "[bench] algorithms" >&2
"$PY" scripts/bench_algorithms.py --out "$OUT" > /dev/null
echo "[bench] process (Dask LocalCluster vs one plain loop)" >&2
"$PY" scripts/bench_process.py --out "$OUT" > /dev/null
echo "[bench] live viewer (30 s against the default pipeline)" >&2
"$PY" scripts/bench_viewer.py --out "$OUT" > /dev/null
echo "[bench] modem link" >&2
"$PY" scripts/bench_modem.py --out "$OUT/modem.json" > "$OUT/modem.txt"
{
  echo "# trapflow benchmark, $(date -u '+%Y-%m-%d %H:%M UTC'), $(nproc) cores"
  echo
  for md in "$OUT"/transport.md "$OUT"/remote.md "$OUT"/shm.md "$OUT"/synth.md \
            "$OUT"/bench_algorithms.md "$OUT"/process.md "$OUT"/viewer.md; do
    [ -f "$md" ] && cat "$md" && echo
  done
  echo "## Modem link"
  echo
  echo '```'
  cat "$OUT/modem.txt"
  echo '```'
} > "$OUT/bench.md"
echo "[bench] wrote $OUT/bench.md" >&2
