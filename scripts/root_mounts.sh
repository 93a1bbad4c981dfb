# Sourced by the scripts that run trapflow inside a Debian root at $root (arm64_check.sh,
# debian_check.sh): mounts into the root, every one undone on exit (bound, then made
# private: nothing mounted under it reaches the host's tree).
# shellcheck shell=bash
mounted=()
unmount_all() {
  for ((i = ${#mounted[@]} - 1; i >= 0; i--)); do umount -l "${mounted[$i]}" || true; done
}
trap unmount_all EXIT
bind() {  # bind-mount a host path (or $2) onto this path in the root, unmounted on exit
  mountpoint -q "$root$1" && return
  [ -e "$root$1" ] || mkdir -p "$root$1"
  mount --bind "${2:-$1}" "$root$1"
  mount --make-private "$root$1"
  mounted+=("$root$1")
}
mount_system() {  # the host's /proc, /sys and /dev; a /dev/shm of the root's own (tmpfs)
  for dir in /proc /sys /dev /dev/pts; do bind "$dir"; done
  if ! mountpoint -q "$root/dev/shm"; then
    mkdir -p "$root/dev/shm"
    mount -t tmpfs -o size=50%,mode=1777 tmpfs "$root/dev/shm"
    mounted+=("$root/dev/shm")
  fi
}
