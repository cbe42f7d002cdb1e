#!/usr/bin/env bash
# The README demo (scripts/demo.sh) on the binaries already built: it must
# exit 0 and print its PSNR line with a mean PSNR of at least FLOOR dB.
# Usage: demo_test.sh REPO_ROOT FLOOR_DB
set -euo pipefail
root=$1
floor=$2
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
if ! log=$(FD_DEMO_SKIP_BUILD=1 FD_DEMO_OUT="$out/demo" "$root/scripts/demo.sh" 2>&1); then
  echo "$log"
  echo "demo_test: scripts/demo.sh failed"
  exit 1
fi
if ! line=$(grep '^demo: PSNR ' <<<"$log"); then
  echo "$log"
  echo "demo_test: the demo printed no 'demo: PSNR' line"
  exit 1
fi
echo "$line"
psnr=$(sed 's/^demo: PSNR \([0-9.]*\) dB.*/\1/' <<<"$line")
[[ -s $out/demo/contact_sheet.png ]] || { echo "demo_test: no contact sheet"; exit 1; }
if ! awk -v p="$psnr" -v f="$floor" 'BEGIN { exit !(p >= f) }'; then
  echo "demo_test: demo PSNR $psnr dB is below the floor $floor dB"
  exit 1
fi
