#!/bin/sh
# The indexer image's default command: a one-shot job that builds the index from the reference
# images mounted at /images into $HMPF_INDEX (default /data/index), unless it has a current
# version already. HMPF_CONFIG: a preset name (default "default") or a YAML file mounted in.
# To add a version to an existing index, run hmpf-index yourself (hmpf-index build --help).
set -eu
index=${HMPF_INDEX:-/data/index}
if [ -f "$index/CURRENT" ]; then
    echo "index exists: $index (version $(cat "$index/CURRENT"))"
    exit 0
fi
exec hmpf-index build --config "${HMPF_CONFIG:-default}" --images "${HMPF_IMAGES_DIR:-/images}" \
    --index "$index" --resume --quiet
