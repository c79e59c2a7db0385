#!/usr/bin/env bash
# Camera frames that no vigproc setting was tuned on, for `vigproc bench clean --images OUT`.
#
# Usage: bash scripts/heldout_frames.sh SNAPSHOT OUT
#   SNAPSHOT  a checkout of github.com/drewnoakes/metadata-extractor-images (a work tree, or
#             a bare git directory such as a mirror's repo/); its README: "You are free to
#             use these media files however you wish."
#   OUT       folder to fill with its jpg/ files (never committed here)
#
# Files byte-identical to one in ../shared/data/jpeg_exif (the frames the clean protocol and
# its tuning read) are left out; blobs a partial snapshot lacks are skipped. bench clean
# keeps the frames whose long side is at least 1000 px.
set -euo pipefail
[ $# -eq 2 ] || { echo "usage: $0 SNAPSHOT OUT" >&2; exit 2; }
snap=$1
out=$2
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
shared="$root/../shared/data/jpeg_exif"
[ -d "$shared" ] || { echo "$0: $shared not found" >&2; exit 2; }
mkdir -p "$out"
known=$(mktemp)
trap 'rm -f "$known"' EXIT
find "$shared" -type f \( -iname '*.jpg' -o -iname '*.jpeg' \) -exec sha256sum {} + | cut -d' ' -f1 | sort -u >"$known"
kept=0
skipped=0
while IFS= read -r -d '' entry; do
    obj=$(printf '%s' "$entry" | cut -d' ' -f3 | cut -f1)
    path=${entry#*$'\t'}
    case "${path,,}" in *.jpg | *.jpeg) ;; *) continue ;; esac
    dest="$out/$(basename -- "$path")"
    if ! git -C "$snap" cat-file blob "$obj" >"$dest.part" 2>/dev/null; then
        rm -f -- "$dest.part"
        skipped=$((skipped + 1))
        continue
    fi
    if grep -qx "$(sha256sum "$dest.part" | cut -d' ' -f1)" "$known"; then
        rm -f -- "$dest.part"
        continue
    fi
    mv -- "$dest.part" "$dest"
    kept=$((kept + 1))
done < <(git -C "$snap" ls-tree -r -z HEAD jpg)
echo "$kept frames in $out ($skipped blobs absent from the snapshot)"
