#!/usr/bin/env bash
# trapflow on arm64 (aarch64) under emulation on an amd64 Debian or Ubuntu host: a Debian
# arm64 root made by debootstrap and run through qemu-user-static and binfmt_misc, its own
# Python, trapflow and every dependency installed from wheels only (pip --only-binary=:all:),
# then the quick start from an empty folder and the unit tier. Writes the aarch64 wheels
# installed (name, version, wheel tag) and the outcome into REPORT_DIR.
#
# Every instruction is emulated: the times printed here are not performance numbers. Run
# scripts/bench.sh --pi on the device itself for those.
#
# Needs root (debootstrap, chroot, mounts) and Debian's archive and the Python package index
# reachable. The arm64 root is kept (the second run skips debootstrap); delete ROOT_DIR to
# start again.
# Usage: sudo scripts/arm64_check.sh [--no-unit] [ROOT_DIR] [REPORT_DIR]
#   ROOT_DIR   the arm64 root (default: ~/.cache/trapflow-arm64)
#   REPORT_DIR where wheels.txt and result.txt go (default: arm64-results)
#   SUITE      Debian release of the root (default: bookworm, Python 3.11)
#   MIRROR     Debian mirror for debootstrap (default: debootstrap's own)
#   DURATION   seconds of the quick start (default: 30; emulation starts processes slowly)
#   HOST_CA    CA bundle the root's pip trusts (default: the host's own)
#   STARTUP_S  supervisor.startup_timeout_s of the quick start (default: 900)
set -euo pipefail
src=$(cd "$(dirname "$0")/.." && pwd)
unit=1
if [ "${1:-}" = "--no-unit" ]; then unit=0; shift; fi
case "${1:-}" in
  -h|--help) sed -n '2,20p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
  -*) echo "scripts/arm64_check.sh: unknown option $1 (expected --no-unit, --help)" >&2; exit 2 ;;
esac
root=${1:-${XDG_CACHE_HOME:-$HOME/.cache}/trapflow-arm64}
report=$(mkdir -p "${2:-arm64-results}" && cd "${2:-arm64-results}" && pwd)
suite=${SUITE:-bookworm}
duration=${DURATION:-30}
say() { echo "[arm64] $(date -u +%H:%M:%S) $*" >&2; }

if [ "$(id -u)" != 0 ]; then
  echo "scripts/arm64_check.sh: needs root (debootstrap, chroot and mounts); run it with sudo" >&2
  exit 2
fi

# 1. Emulation: qemu-user-static registers aarch64 with binfmt_misc (F flag: the
#    interpreter is opened once at registration, so it works inside the chroot too).
if ! command -v qemu-aarch64-static > /dev/null || ! command -v debootstrap > /dev/null; then
  say "installing qemu-user-static, binfmt-support, debootstrap"
  apt-get update -q > /dev/null
  DEBIAN_FRONTEND=noninteractive apt-get install -y -q qemu-user-static binfmt-support \
    debootstrap > /dev/null
fi
if [ ! -e /proc/sys/fs/binfmt_misc/status ]; then
  mount binfmt_misc -t binfmt_misc /proc/sys/fs/binfmt_misc
fi
if [ ! -e /proc/sys/fs/binfmt_misc/qemu-aarch64 ]; then
  update-binfmts --enable qemu-aarch64
fi
grep -q '^enabled' /proc/sys/fs/binfmt_misc/qemu-aarch64 || {
  echo "scripts/arm64_check.sh: binfmt_misc has qemu-aarch64 but it is disabled;" \
       "run: update-binfmts --enable qemu-aarch64" >&2; exit 1; }

# 2. An arm64 Debian root with its Python (kept between runs).
if [ ! -x "$root/usr/bin/python3" ]; then
  say "debootstrap --arch arm64 $suite into $root (10 to 30 minutes under emulation)"
  debootstrap --arch arm64 --variant=minbase \
    --include=python3,python3-venv,ca-certificates "$suite" "$root" ${MIRROR:+"$MIRROR"} \
    > "$report/debootstrap.log"
fi
# shellcheck source=scripts/root_mounts.sh
. "$src/scripts/root_mounts.sh"
# A /dev/shm of its own: qemu-user fakes /proc/self/stat, so the frame ring's owner start
# time differs from the one the host sees, and a pipeline started on the host would take
# the emulated pipeline's ring for a dead process's and remove it (and the reverse).
mount_system
# qemu-user passes the host's /proc/cpuinfo through: onnxruntime's CPU detection finds no
# ARM core in an x86 one and crashes at import (SIGSEGV). The root sees Cortex-A76 cores
# (a Pi 5's), as many as the host has, which also matches /sys/devices/system/cpu.
for ((cpu = 0; cpu < $(nproc); cpu++)); do
  printf 'processor\t: %d\nBogoMIPS\t: 108.00\nFeatures\t: fp asimd evtstrm aes pmull sha1 sha2 crc32 atomics fphp asimdhp cpuid asimdrdm lrcpc dcpop asimddp\nCPU implementer\t: 0x41\nCPU architecture: 8\nCPU variant\t: 0x4\nCPU part\t: 0xd0b\nCPU revision\t: 1\n\n' "$cpu"
done > "$root/etc/cpuinfo-arm64"
bind /proc/cpuinfo "$root/etc/cpuinfo-arm64"
cp -L /etc/resolv.conf "$root/etc/resolv.conf"
# The root trusts what the host trusts (a site's TLS proxy included): pip inside it uses
# the host's CA bundle.
host_ca=${HOST_CA:-/etc/ssl/certs/ca-certificates.crt}
ca_env=()
if [ -f "$host_ca" ]; then
  cp -L "$host_ca" "$root/etc/ssl/certs/host-ca-certificates.crt"
  ca_env=(PIP_CERT=/etc/ssl/certs/host-ca-certificates.crt
          SSL_CERT_FILE=/etc/ssl/certs/host-ca-certificates.crt)
fi
# A clean environment inside: the host's pip settings (its indexes, constraints, local
# wheel folders) name paths the arm64 root does not have.
chroot_bin=$(command -v chroot)
in_root() {
  env -i PATH=/opt/venv/bin:/usr/local/bin:/usr/bin:/bin HOME=/root LANG=C.UTF-8 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 "${ca_env[@]}" "$chroot_bin" "$root" "$@"
}
arch=$(in_root python3 -c 'import platform, sys; print(platform.machine(), sys.version.split()[0])')
say "arm64 Python: $arch"
case "$arch" in
  aarch64*) ;;
  *) echo "scripts/arm64_check.sh: expected an aarch64 Python in $root, got '$arch'" >&2; exit 1 ;;
esac

# 3. trapflow as a wheel (pure Python, built here from the tracked files), and every
#    dependency from wheels only: a package without an aarch64 wheel fails the install.
rm -rf "$root/opt/src" "$root/opt/dist"
mkdir -p "$root/opt/src" "$root/opt/dist"
(cd "$src" && git ls-files -z --cached --others --exclude-standard | tar -c --null -T - -f -) \
  | tar -x -C "$root/opt/src"
python3 -m pip wheel --quiet --no-deps --wheel-dir "$root/opt/dist" "$root/opt/src"
wheel=$(cd "$root/opt/dist" && ls trapflow-*.whl)
# The unit tier's own needs (tests/unit imports these beyond the run-time dependencies),
# and optional extras tried one by one: one without an aarch64 wheel is reported, and the
# tests that need it skip (the tags extra: the AprilTags plugin has a fallback without it).
test_deps=(pytest pytest-timeout onnx foxglove-schemas-protobuf)
optional=(pupil-apriltags)
if [ ! -x "$root/opt/venv/bin/python" ]; then
  in_root python3 -m venv /opt/venv
  in_root python -m pip install --quiet --upgrade --only-binary=:all: pip
fi
say "pip install --only-binary=:all: $wheel ${test_deps[*]}"
t0=$(date +%s)
in_root python -m pip install --quiet --only-binary=:all: "/opt/dist/$wheel" "${test_deps[@]}"
# The same version number on a later run: this tree's trapflow replaces the installed one.
in_root python -m pip install --quiet --no-deps --force-reinstall "/opt/dist/$wheel"
say "installed in $(( $(date +%s) - t0 )) s"
missing=()
for dep in "${optional[@]}"; do
  if ! in_root python -m pip install --quiet --only-binary=:all: "$dep" 2> /dev/null; then
    missing+=("$dep")
    say "optional $dep: no wheel for aarch64 / Python $(echo "$arch" | cut -d' ' -f2) (its tests skip)"
  fi
done

# 4. Which wheels came: name, version and the wheel's tag (aarch64 or pure).
in_root python - > "$report/wheels.txt" <<'PY'
import importlib.metadata as md, platform, sys
print(f"# {platform.machine()}, Python {sys.version.split()[0]}; name version tag(s)")
rows = []
for dist in md.distributions():
    text = dist.read_text("WHEEL") or ""
    tags = sorted({line.split(":", 1)[1].strip() for line in text.splitlines()
                   if line.startswith("Tag:")})
    rows.append((dist.metadata["Name"].lower(), dist.version, " ".join(tags) or "?"))
for name, version, tags in sorted(rows):
    print(f"{name} {version} {tags}")
PY
native=$(tail -n +2 "$report/wheels.txt" | grep -c aarch64 || true)
say "$(($(wc -l < "$report/wheels.txt") - 1)) wheels, $native of them built for aarch64: $report/wheels.txt"

# 5. The quick start from an empty folder, with the installed trapflow (not the source).
# Emulated, each process takes tens of seconds to import and capture minutes to build the
# synthetic world: a start-up limit of STARTUP_S (default 900) instead of 60 s, and a
# pair may take the pools' workers longer than their 10 s timeout_s.
say "quick start: trapflow start --workers mono=1,stereo=1,vo=1 --duration $duration"
rm -rf "$root/opt/quick" && mkdir -p "$root/opt/quick"
printf 'supervisor:\n  startup_timeout_s: %s\npools:\n' "${STARTUP_S:-900}" \
  > "$root/opt/quick/emulated.yaml"
for pool in mono stereo vo; do
  printf '  %s: {timeout_s: 300.0}\n' "$pool" >> "$root/opt/quick/emulated.yaml"
done
t0=$(date +%s)
in_root sh -c "cd /opt/quick && trapflow start --config emulated.yaml \
  --workers mono=1,stereo=1,vo=1 --duration $duration" > "$report/quickstart.txt" 2>&1 || {
  tail -20 "$report/quickstart.txt" >&2; echo "[arm64] quick start FAILED" >&2; exit 1; }
lines=$(wc -l < "$root/opt/quick/runs/latest/results.jsonl")
pools=$(in_root python -c "
import json, collections
c = collections.Counter(k for line in open('/opt/quick/runs/latest/results.jsonl')
                        for k in json.loads(line))
print(', '.join(f'{k} {n}' for k, n in sorted(c.items())))")
[ "$lines" -gt 0 ] || { echo "[arm64] quick start wrote no result line" >&2; exit 1; }
quick="quick start: $lines result lines ($pools) in $(( $(date +%s) - t0 )) s wall"
say "$quick"

# 6. The unit tier, from the source tree against the installed dependencies.
unit_line="unit tier: not run (--no-unit)"
if [ "$unit" = 1 ]; then
  say "unit tier: python -m pytest tests/unit -q -p no:randomly (13-17 minutes emulated on 2 busy cores)"
  t0=$(date +%s)
  set +e
  in_root sh -c "cd /opt/src && python -m pytest tests/unit -q -p no:randomly -p no:cacheprovider \
    -o timeout=1200" > "$report/unit.txt" 2>&1
  rc=$?
  set -e
  unit_line="unit tier: $(tail -1 "$report/unit.txt") (exit $rc) in $(( $(date +%s) - t0 )) s wall"
  say "$unit_line"
  [ "$rc" = 0 ] || { grep -E '^(FAILED|ERROR)' "$report/unit.txt" | head -20 >&2; }
fi
{
  echo "arm64 under emulation, $(date -u '+%Y-%m-%d %H:%M UTC'), host $(uname -m) $(nproc) cores"
  echo "root: Debian $suite arm64; $(head -1 "$report/wheels.txt" | sed 's/^# //')"
  echo "install: pip --only-binary=:all: $wheel ${test_deps[*]}: ok"
  echo "optional without an aarch64 wheel: ${missing[*]:-none}"
  echo "$quick"
  echo "$unit_line"
  echo "(times under emulation are not performance numbers)"
} | tee "$report/result.txt"
[ "$unit" = 0 ] || [ "$rc" = 0 ]
