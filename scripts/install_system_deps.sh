#!/usr/bin/env bash
# Installs the Debian/Ubuntu shared libraries that open3d (libusb) and bpy (X11/GL client libs) load, and
# bubblewrap, the sandbox evaluate runs every method in (selfseg/eval/sandbox.py), and a headless Chromium
# (Debian's chromium-headless-shell, ~220 MB, no GTK: smaller than chromium) for tests/test_report.py's check
# that the inspect report draws its 3-D panels in a real browser.
# Idempotent: does nothing when they are all present.
set -euo pipefail
pkgs=(libusb-1.0-0 libx11-6 libxrender1 libxxf86vm1 libxfixes3 libxi6 libxkbcommon0 libsm6 libice6 libgl1 libegl1 libgomp1
      bubblewrap chromium-headless-shell)
command -v dpkg-query >/dev/null || { echo "install_system_deps: not a Debian-like system; make sure these are installed: ${pkgs[*]}" >&2; exit 0; }
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
echo "install_system_deps: installing ${missing[*]}"
$SUDO apt-get update -qq
if ! apt-cache show chromium-headless-shell >/dev/null 2>&1; then  # e.g. Ubuntu, where Chromium is a snap
  echo "install_system_deps: no chromium-headless-shell package here; tests/test_report.py's browser check needs chromium on PATH" >&2
  keep=(); for p in "${missing[@]}"; do [ "$p" = chromium-headless-shell ] || keep+=("$p"); done; missing=("${keep[@]}")
  [ ${#missing[@]} -eq 0 ] && exit 0
fi
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
