#!/usr/bin/env bash
# Regenerates src/x86_64.rs and src/aarch64.rs, the raw V4L2 bindings, from the kernel's V4L2
# UAPI header (linux/videodev2.h), with bindgen 0.65.1 (the version, and the default options,
# the upstream v4l2-sys-mit 0.3.0 generates with at build time). Needs libclang and the
# headers of both targets; on Debian 12:
#   apt-get install libclang-dev linux-libc-dev libc6-dev \
#     linux-libc-dev-arm64-cross libc6-dev-arm64-cross
# Generated on Debian 12 (linux-libc-dev 6.1) with: ./generate.sh
set -euo pipefail
cd "$(dirname "$0")"
here=$(pwd)
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$here/generate/target}"
cargo build --release --manifest-path generate/Cargo.toml
gen="$CARGO_TARGET_DIR/release/v4l2-sys-mit-generate"
# x86_64: the host's headers (/usr/include with its x86_64-linux-gnu multiarch directory).
"$gen" x86_64-unknown-linux-gnu / src/x86_64.rs
# aarch64: the same kernel UAPI headers (linux/ and asm-generic/ do not depend on the
# architecture), with Debian's cross headers for asm/ and the C library
# (/usr/aarch64-linux-gnu/include), so both files follow one kernel version.
uapi=$(mktemp -d)
trap 'rm -rf "$uapi"' EXIT
ln -s /usr/include/linux "$uapi/linux"
ln -s /usr/include/asm-generic "$uapi/asm-generic"
"$gen" aarch64-unknown-linux-gnu /usr/aarch64-linux-gnu src/aarch64.rs "$uapi"
echo "generated src/x86_64.rs and src/aarch64.rs"
