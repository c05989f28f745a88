#!/usr/bin/env bash
# Generates the Python stubs of FaStage's contract (proto/stage/v1, and grpc.health.v1) with Debian's protoc and its
# gRPC Python plugin (packages protobuf-compiler, protobuf-compiler-grpc; scripts/bootstrap installs them).
# Usage: examples/python/generate.sh [OUT_DIR]   (default: examples/python/generated)
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
proto="$here/../../proto"
out="${1:-$here/generated}"
mkdir -p "$out"
cd "$proto"
protoc -I. --python_out="$out" --grpc_out="$out" --plugin=protoc-gen-grpc=/usr/bin/grpc_python_plugin \
  stage/v1/*.proto grpc/health/v1/health.proto
echo "stubs of $(ls stage/v1/*.proto | wc -l) contract files in $out" >&2
