#!/usr/bin/env bash
# The README's quick start on a fresh Debian 13 (trixie), for real: a minimal root made by
# debootstrap (minbase), the README's own `sudo apt install ...` for it (nothing else), the
# repository's tracked files copied into an ordinary user's home, and the quick-start
# command line taken verbatim from README.md and run there as that user. Then every pool
# (mono, stereo, vo) must have result lines in the run directory; one summary line at the
# end.
#
# Needs root (debootstrap, chroot, mounts), and Debian's archive (the mirror this machine's
# apt already uses) and the Python package index reachable. The root is kept in CACHE_DIR
# (a rerun skips debootstrap); the user, the copy and its venv are made anew every run.
# Delete CACHE_DIR to start from nothing again.
# Usage: sudo scripts/debian_check.sh [CACHE_DIR]
#   CACHE_DIR  where the Debian root is kept (default: ~/.cache/trapflow-debian13)
#   SUITE      Debian release of the root (default: trixie, Debian 13)
#   MIRROR     Debian mirror for debootstrap (default: the one apt uses on this machine)
#   HOST_CA    CA bundle pip trusts inside the root (default: this machine's, which knows
#              a site's TLS proxy; HOST_CA= for the root's own ca-certificates alone)
set -euo pipefail
src=$(cd "$(dirname "$0")/.." && pwd)
case "${1:-}" in
  -h|--help) sed -n '2,18p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
  -*) echo "scripts/debian_check.sh: unknown option $1 (expected --help)" >&2; exit 2 ;;
esac
root=${1:-${XDG_CACHE_HOME:-$HOME/.cache}/trapflow-debian13}
root=${root%/}
suite=${SUITE:-trixie}
user=trapper
say() { echo "[debian] $(date -u +%H:%M:%S) $*" >&2; }
die() { echo "scripts/debian_check.sh: $*" >&2; exit 1; }

[ "$(id -u)" = 0 ] || { echo "scripts/debian_check.sh: needs root (debootstrap, chroot and mounts); run it with sudo" >&2; exit 2; }

# The README's two lines: its install hint (`sudo apt install ...`, first mention) and the
# quick start (the first command line of its first shell block).
# shellcheck disable=SC2016  # backquotes, not an expansion
apt_line=$(grep -o -m1 '`sudo apt install [^`]*`' "$src/README.md" | tr -d '`') \
  || die "README.md names no \`sudo apt install ...\`"
quick=$(awk '/^```sh/ {inside = 1; next} /^```/ && inside {exit}
             inside && NF && !/^[[:space:]]*#/ {print; exit}' "$src/README.md")
[ -n "$quick" ] || die "README.md has no command line in its first \`\`\`sh block"
say "README install hint: $apt_line"
say "README quick start:  $quick"

# The mirror apt uses here: the source whose suite is this machine's own release
# (one-line sources.list entries or deb822 .sources files).
host_mirror() {
  local codename files
  codename=$(sed -n 's/^VERSION_CODENAME=//p' /etc/os-release | tr -d '"')
  files=$(ls /etc/apt/sources.list /etc/apt/sources.list.d/*.list \
              /etc/apt/sources.list.d/*.sources 2> /dev/null || true)
  [ -n "$codename" ] && [ -n "$files" ] || return 0
  # shellcheck disable=SC2086  # the file names have no spaces
  awk -v want="$codename" '
    FNR == 1 { uris = ""; suites = ""; enabled = 1 }
    /^deb[[:space:]]/ {  # deb [options] URI suite components
      i = 2; if ($i ~ /^\[/) { while ($i !~ /\]$/) i++; i++ }
      if ($(i + 1) == want) { print $i; exit }
      next }
    /^URIs:/ { uris = $2 } /^Suites:/ { suites = $0 } /^Enabled:[[:space:]]*no/ { enabled = 0 }
    /^[[:space:]]*$/ { uris = ""; suites = ""; enabled = 1 }
    uris != "" && suites != "" && enabled {
      n = split(suites, s, /[[:space:]]+/)
      for (k = 2; k <= n; k++) if (s[k] == want) { print uris; exit }
    }' $files | head -1
}
mirror=${MIRROR:-$(host_mirror)}
[ -n "$mirror" ] || die "no Debian mirror found in /etc/apt/sources.list{,.d}; set MIRROR"

if ! command -v debootstrap > /dev/null; then
  say "installing debootstrap"
  apt-get update -q > /dev/null
  DEBIAN_FRONTEND=noninteractive apt-get install -y -q debootstrap > /dev/null
fi

t_start=$(date +%s)
# 1. A minimal Debian root (kept between runs).
if [ ! -e "$root/.debootstrap-done" ]; then
  say "debootstrap --variant=minbase $suite into $root from $mirror"
  rm -rf "$root"
  mkdir -p "$(dirname "$root")"
  debootstrap --variant=minbase "$suite" "$root" "$mirror" > "$root.debootstrap.log" 2>&1 \
    || { tail -20 "$root.debootstrap.log" >&2; die "debootstrap failed"; }
  touch "$root/.debootstrap-done"
fi

# 2. Mounts, every one undone on exit (bound, then made private: nothing mounted under it
#    reaches the host's tree). /dev/shm is a tmpfs of the root's own, as in a container.
# shellcheck source=scripts/root_mounts.sh
. "$src/scripts/root_mounts.sh"
mount_system
cp -L /etc/resolv.conf "$root/etc/resolv.conf"
ca_env=()
host_ca=${HOST_CA-/etc/ssl/certs/ca-certificates.crt}
if [ -n "$host_ca" ] && [ -f "$host_ca" ]; then
  cp -L "$host_ca" "$root/etc/host-ca.crt"
  ca_env=(PIP_CERT=/etc/host-ca.crt SSL_CERT_FILE=/etc/host-ca.crt)
fi
# A clean environment inside: this machine's pip settings name paths the root lacks.
chroot_bin=$(command -v chroot)
in_root() {  # in_root USER COMMAND...
  local who=$1 home=/root ids=0:0
  shift
  if [ "$who" != root ]; then  # numeric: the host has no such user
    home=/home/$who
    ids=$(awk -F: -v u="$who" '$1 == u {print $3 ":" $4}' "$root/etc/passwd")
  fi
  # shellcheck disable=SC2016  # expanded by the root's bash
  env -i PATH=/usr/local/bin:/usr/bin:/bin HOME="$home" USER="$who" LANG=C.UTF-8 TERM=dumb \
    "${ca_env[@]}" "$chroot_bin" --userspec="$ids" "$root" \
    /bin/bash -c 'cd "$HOME" && eval "$1"' bash "$*"
}

# 3. What the README says a user installs (as root: the root has no sudo), and nothing else.
pkgs=${apt_line#sudo apt install }
say "in the root: apt-get install $pkgs"
in_root root "DEBIAN_FRONTEND=noninteractive apt-get update -q > /dev/null && \
  DEBIAN_FRONTEND=noninteractive apt-get install -y -q $pkgs > /tmp/apt.log 2>&1" \
  || { tail -20 "$root/tmp/apt.log" >&2; die "apt-get install $pkgs failed"; }
py=$(in_root root "python3 -c 'import sys; print(sys.version.split()[0])'")
debver=$(cat "$root/etc/debian_version")
say "Debian $debver, Python $py; ca-certificates: $(in_root root \
  "dpkg-query -W -f='\${Status}' ca-certificates 2> /dev/null | grep -q 'ok installed' \
   && echo 'installed (pulled in by $pkgs)' || echo 'not installed'")"

# 4. An ordinary user with the repository's tracked files in ~/trapflow, made anew.
# (minbase has no useradd: the passwd and group lines are written here, uid 1000.)
if ! grep -q "^$user:" "$root/etc/passwd"; then
  echo "$user:x:1000:1000::/home/$user:/bin/bash" >> "$root/etc/passwd"
  echo "$user:x:1000:" >> "$root/etc/group"
fi
rm -rf "${root:?}/home/${user:?}"
mkdir -p "$root/home/$user"
mkdir -p "$root/home/$user/trapflow"
(cd "$src" && git ls-files -z | tar -c --null -T - -f -) | tar -x -C "$root/home/$user/trapflow"
chown -R 1000:1000 "$root/home/$user"

# 5. The quick start, verbatim, as the user from the checkout.
say "as $user in ~/trapflow: $quick"
t0=$(date +%s)
set +e
in_root "$user" "cd trapflow && $quick" > "$root/home/$user/quickstart.txt" 2>&1
rc=$?
set -e
secs=$(( $(date +%s) - t0 ))
results="$root/home/$user/trapflow/runs/latest/results.jsonl"
if [ "$rc" != 0 ] || [ ! -s "$results" ]; then
  tail -30 "$root/home/$user/quickstart.txt" >&2
  die "quick start failed (exit $rc) after $secs s; its output: $root/home/$user/quickstart.txt"
fi

# 6. Result lines from every pool: mono_ir (mono), stereo_ir (stereo), stereo_vo (vo).
counts=$(python3 - "$results" <<'PY'
import collections, json, sys
kinds = collections.Counter(k for line in open(sys.argv[1]) if line.strip()
                            for k in json.loads(line))
pools = {"mono": "mono_ir", "stereo": "stereo_ir", "vo": "stereo_vo"}
print(" ".join(f"{pool}={kinds.get(kind, 0)}" for pool, kind in pools.items()))
PY
)
total=$(wc -l < "$results")
summary="Debian $debver ($suite), Python $py: quick start ok in $secs s as $user, $total result lines ($counts); whole check $(( $(date +%s) - t_start )) s"
case " $counts " in
  *"=0 "*) echo "[debian] FAILED: a pool has no result line: $summary"; exit 1 ;;
esac
echo "[debian] $summary"
