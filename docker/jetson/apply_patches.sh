#!/usr/bin/env bash
# Apply docker/jetson/patches/*.patch to the imported Jazzy sources, in name order.
#   apply_patches.sh SRC_DIR PATCH_DIR
# Each patch names its repository (the folder under SRC_DIR that `vcs import` made) in a
# "Repository: <folder>" line and says why in a "Reason: ..." line, both above the diff.
# A patch that does not apply stops the build (the pinned tags changed under it).
set -euo pipefail
src=$1
patches=$2
shopt -s nullglob
applied=0
for patch in "$patches"/*.patch; do
  repo=$(sed -n 's/^Repository: *//p' "$patch" | head -1)
  reason=$(sed -n 's/^Reason: *//p' "$patch" | head -1)
  [ -n "$repo" ] && [ -d "$src/$repo" ] || { echo "[patches] $patch: no 'Repository:' folder under $src" >&2; exit 1; }
  echo "[patches] $(basename "$patch") -> $repo: $reason"
  git -C "$src/$repo" apply --verbose "$(realpath "$patch")"
  applied=$((applied + 1))
done
echo "[patches] $applied applied"
