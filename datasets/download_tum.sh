#!/usr/bin/env bash
# Downloads official TUM RGB-D sequences and checks them.
#
# Usage: datasets/download_tum.sh [--dir DIR] [--keep-archive] NAME...
#   NAME is a sequence name such as freiburg1_xyz, freiburg2_desk or
#   rgbd_dataset_freiburg3_long_office_household (the "rgbd_dataset_" prefix is optional).
#   Each sequence ends up in DIR/rgbd_dataset_NAME/ (default DIR: data/tum).
#
# For every sequence: the transfer must complete (bytes received == Content-Length), the
# archive must list and extract cleanly, and rgb.txt, depth.txt, rgb/ and depth/ must exist
# (groundtruth.txt too, except for the benchmark's hidden-ground-truth sequences, which only
# warn). The archive's sha256 is printed so it can be recorded.
set -euo pipefail

BASE_URL="https://cvg.cit.tum.de/rgbd/dataset"
DIR="data/tum"
KEEP=0

usage() {
    sed -n '2,12p' "$0" | sed 's/^# \{0,1\}//'
}

die() {
    echo "download_tum: $*" >&2
    exit 1
}

names=()
while [[ $# -gt 0 ]]; do
    case "$1" in
        -h|--help) usage; exit 0 ;;
        --dir) [[ $# -ge 2 ]] || die "--dir needs a folder"; DIR="$2"; shift 2 ;;
        --dir=*) DIR="${1#--dir=}"; shift ;;
        --keep-archive) KEEP=1; shift ;;
        -*) die "unknown option $1 (see --help)" ;;
        *) names+=("$1"); shift ;;
    esac
done
[[ ${#names[@]} -gt 0 ]] || { usage >&2; exit 2; }
for tool in curl tar sha256sum; do
    command -v "$tool" >/dev/null || die "$tool is required"
done
mkdir -p "$DIR"

fetch_one() {
    local name="${1#rgbd_dataset_}"
    [[ "$name" =~ ^freiburg([123])_[a-z0-9_]+$ ]] || die "not a TUM sequence name: $1 (e.g. freiburg1_xyz)"
    local fr="freiburg${BASH_REMATCH[1]}"
    local seq="rgbd_dataset_${name}"
    local url="${BASE_URL}/${fr}/${seq}.tgz"
    local tgz="${DIR}/${seq}.tgz"
    local part="${tgz}.part"

    echo "== ${seq}: ${url}"
    # Expected size from the final response's Content-Length (after redirects).
    local expected
    expected=$(curl -sfIL "$url" | tr -d '\r' | awk 'tolower($1)=="content-length:" {n=$2} END {print n}') \
        || die "${seq}: HEAD request failed (${url})"
    [[ "$expected" =~ ^[0-9]+$ ]] || die "${seq}: server sent no Content-Length"

    local got
    got=$(curl -fL --retry 3 --retry-delay 5 -C - -o "$part" -w '%{size_download}' "$url") \
        || die "${seq}: download failed"
    local size
    size=$(stat -c %s "$part")
    [[ "$size" == "$expected" ]] || die "${seq}: incomplete transfer: ${size} of ${expected} bytes (this run: ${got})"
    tar -tzf "$part" >/dev/null || die "${seq}: archive is corrupt"
    mv "$part" "$tgz"

    tar -xzf "$tgz" -C "$DIR" || die "${seq}: extraction failed"
    local out="${DIR}/${seq}"
    for f in rgb.txt depth.txt; do
        [[ -s "${out}/${f}" ]] || die "${seq}: ${f} missing after extraction"
    done
    for d in rgb depth; do
        [[ -d "${out}/${d}" ]] || die "${seq}: ${d}/ missing after extraction"
    done
    if [[ ! -s "${out}/groundtruth.txt" ]]; then
        echo "warning: ${seq} has no groundtruth.txt (hidden-ground-truth benchmark sequence?)" >&2
    fi
    local n_rgb
    n_rgb=$(grep -vc '^#' "${out}/rgb.txt" || true)
    local sum
    sum=$(sha256sum "$tgz" | cut -d' ' -f1)
    echo "ok ${seq}: ${n_rgb} colour frames in ${out}"
    echo "sha256 ${sum}  ${seq}.tgz"
    if [[ $KEEP -eq 0 ]]; then
        rm -f "$tgz"
    fi
}

for n in "${names[@]}"; do
    fetch_one "$n"
done
