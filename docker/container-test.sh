#!/usr/bin/env bash
# make container-test: build both images on a local base, run the indexer job over Gardens
# Point day_right, start the service with API keys on, and localize a night_right frame
# through the published port. Containers and the work folder are removed on any exit.
#
# Made for a machine with podman and runc (make container-test installs them, with mmdebstrap)
# that reaches Debian's mirror and PyPI but no container registry (docs/deployment-container.md).
# Environment (all optional):
#   HMPF_DATASETS      datasets folder (default ../shared/datasets); mounted read-only
#   BASE_IMAGE         base of the images (default: localhost/hmpf-base:bookworm-py311, built by
#                      docker/local-base.sh when missing; give python:3.11-slim-bookworm where a
#                      registry is reachable)
#   CA_BUNDLE          CA certificates for pip inside the build (default: pip's `cert` setting
#                      of this machine, else /etc/ssl/certs/ca-certificates.crt; "none": none)
#   WHEELS             a folder of local wheels (default: pip's `find-links` setting when it is
#                      a folder; "none": none). With it torch comes from there (+cpu wheel),
#                      without it from the PyTorch CPU index.
#   TAG                image tag (default test): localhost/hmpf-indexer:TAG, localhost/hmpf-service:TAG
#   SERVICE_EXTRAS     the service image's extras (the Dockerfile's default when unset)
#   CONTEXT            build context (default the repository root: the working tree as it is)
#   PORT               host port of the service (default 18080)
#   QUERY              night frame (default night_right/Image050.jpg); EXPECT: accepted
#                      reference ids (default 48-52, the frame's place +-2)
#   PODMAN_RUNTIME     OCI runtime (default runc: crun fails on some cgroup v1 hosts)
#   KEEP_IMAGES        1 (default) keeps the images, 0 removes them at the end
# --build-only: build the images (and print their sizes) and stop (make container).
set -euo pipefail
BUILD_ONLY=
[ "${1:-}" != --build-only ] || BUILD_ONLY=1

ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
PODMAN=${PODMAN:-podman}
RUNTIME=${PODMAN_RUNTIME:-runc}
DATASETS=${HMPF_DATASETS:-$(cd "$ROOT/.." && pwd)/shared/datasets}
REFERENCE=$DATASETS/gardens_point/day_right
QUERY=${QUERY:-$DATASETS/gardens_point/night_right/Image050.jpg}
EXPECT=${EXPECT:-48 49 50 51 52}
BASE_IMAGE=${BASE_IMAGE:-localhost/hmpf-base:bookworm-py311}
TAG=${TAG:-test}
INDEXER_IMAGE=localhost/hmpf-indexer:$TAG
SERVICE_IMAGE=localhost/hmpf-service:$TAG
PORT=${PORT:-18080}
CONTEXT=${CONTEXT:-$ROOT}
KEEP_IMAGES=${KEEP_IMAGES:-1}
NAME=hmpf-ct-$$
RUN=("$PODMAN" --runtime="$RUNTIME" run --network=host
     --ulimit nofile=1024:1024 --ulimit nproc=1024:1024)

pip_setting() {  # this machine's pip setting $1 (global., then :env:), empty when unset
    python3 -m pip config list 2>/dev/null \
        | sed -n "s/^\(global\|:env:\)\.$1='\(.*\)'$/\2/p" | head -n 1
}
if [ -z "${CA_BUNDLE:-}" ]; then
    CA_BUNDLE=$(pip_setting cert)
    [ -n "$CA_BUNDLE" ] || CA_BUNDLE=/etc/ssl/certs/ca-certificates.crt
fi
if [ -z "${WHEELS:-}" ]; then
    WHEELS=$(pip_setting find-links | awk '{print $1}')
    [ -d "$WHEELS" ] || WHEELS=none
fi

T0=$(date +%s)
TIMES=()
STEPS=()  # "name=seconds" for RECORD
step_start() { STEP=$1; STEP_T=$(date +%s); echo; echo "== $STEP"; }
step_end() {
    local dt=$(( $(date +%s) - STEP_T ))
    TIMES+=("$(printf '%-32s %5d s' "$STEP" "$dt")")
    STEPS+=("$STEP=$dt")
    echo "-- $STEP: ${dt} s"
}
fail() { echo "container-test FAILED: $*" >&2; exit 1; }

WORK=$(mktemp -d "${TMPDIR:-/tmp}/hmpf-container-test.XXXXXX")
cleanup() {
    local rc=$?
    for c in "$NAME-indexer" "$NAME-keys" "$NAME-service"; do
        "$PODMAN" rm -f -t 5 "$c" >/dev/null 2>&1 || true
    done
    rm -rf "$WORK"
    if [ "$KEEP_IMAGES" = 0 ]; then
        "$PODMAN" rmi -f "$INDEXER_IMAGE" "$SERVICE_IMAGE" >/dev/null 2>&1 || true
    fi
    [ $rc = 0 ] || echo "container-test failed (exit $rc) after $(( $(date +%s) - T0 )) s" >&2
    exit $rc
}
trap cleanup EXIT
trap 'exit 130' INT TERM

[ -n "$BUILD_ONLY" ] || [ -d "$REFERENCE" ] || fail "no reference images at $REFERENCE (HMPF_DATASETS)"
[ -n "$BUILD_ONLY" ] || [ -f "$QUERY" ] || fail "no query frame $QUERY"

# ---- images ------------------------------------------------------------------------------
BASE_KEPT=no  # whether the base image was there before this run (then it is not rebuilt)
"$PODMAN" image exists "$BASE_IMAGE" 2>/dev/null && BASE_KEPT=yes
step_start "base image"
case "$BASE_IMAGE" in
    localhost/hmpf-base:*) "$ROOT/docker/local-base.sh" "$BASE_IMAGE" ;;
    *) echo "base $BASE_IMAGE (pulled by the build when missing)" ;;
esac
step_end

BUILD=("$PODMAN" build --isolation chroot --format docker -f "$CONTEXT/docker/Dockerfile"
       --build-arg "PYTHON_IMAGE=$BASE_IMAGE")  # docker format: keeps the HEALTHCHECK
if [ "$CA_BUNDLE" != none ]; then
    [ -f "$CA_BUNDLE" ] || fail "CA_BUNDLE $CA_BUNDLE is not a file"
    BUILD+=(--secret "id=ca_bundle,src=$CA_BUNDLE")
fi
if [ "$WHEELS" != none ]; then
    # local wheels: torch's CPU wheel by its local version label, from the wheels folder
    BUILD+=(--build-context "wheels=$WHEELS" --build-arg TORCH_INDEX_URL=
            --build-arg "TORCH_VERSION=$(sed -n 's/.*"torch==\([^"]*\)".*/\1/p' "$CONTEXT/pyproject.toml" | head -n 1)+cpu")
fi
[ -z "${SERVICE_EXTRAS:-}" ] || BUILD+=(--build-arg "SERVICE_EXTRAS=$SERVICE_EXTRAS")
echo "build: ${BUILD[*]} (context $CONTEXT; CA_BUNDLE=$CA_BUNDLE WHEELS=$WHEELS)"

step_start "build indexer image"
if ! "${BUILD[@]}" --target indexer -t "$INDEXER_IMAGE" "$CONTEXT" >"$WORK/build-indexer.log" 2>&1; then
    tail -n 40 "$WORK/build-indexer.log" >&2; fail "podman build --target indexer"
fi
tail -n 3 "$WORK/build-indexer.log"
step_end

step_start "build service image"
if ! "${BUILD[@]}" --target service -t "$SERVICE_IMAGE" "$CONTEXT" >"$WORK/build-service.log" 2>&1; then
    tail -n 40 "$WORK/build-service.log" >&2; fail "podman build --target service"
fi
tail -n 3 "$WORK/build-service.log"
step_end

size_mb() { echo $(( $("$PODMAN" image inspect --format '{{.Size}}' "$1") / 1000000 )); }
if "${RUN[@]}" --rm --no-healthcheck "$SERVICE_IMAGE" python -c "import torch" >/dev/null 2>&1; then
    SERVICE_TORCH=yes
else
    SERVICE_TORCH=no
fi

report() {
    printf '%s\n' "${TIMES[@]}"
    printf '%-40s %5d MB\n' "image $INDEXER_IMAGE" "$(size_mb "$INDEXER_IMAGE")" \
        "image $SERVICE_IMAGE" "$(size_mb "$SERVICE_IMAGE")"
    echo "torch in the service image: $SERVICE_TORCH"
}
if [ -n "$BUILD_ONLY" ]; then
    echo; echo "== images built in $(( $(date +%s) - T0 )) s"; report; exit 0
fi

# ---- the indexer job -----------------------------------------------------------------------
# host folders the containers' user (uid 10001) writes: the index, the sequence key, API keys
mkdir -p "$WORK/data" "$WORK/state" "$WORK/secrets"
chown 10001:10001 "$WORK/data" "$WORK/state" "$WORK/secrets" 2>/dev/null \
    || chmod 0777 "$WORK/data" "$WORK/state" "$WORK/secrets"
step_start "indexer job (day_right)"
"${RUN[@]}" --rm --name "$NAME-indexer" \
    -v "$REFERENCE:/images:ro" -v "$WORK/data:/data" "$INDEXER_IMAGE"
[ -f "$WORK/data/index/CURRENT" ] || fail "the indexer job left no $WORK/data/index/CURRENT"
echo "index version $(cat "$WORK/data/index/CURRENT")"
step_end

# ---- the service, keys on --------------------------------------------------------------------
step_start "service start (to /readyz)"
"${RUN[@]}" --rm --no-healthcheck --name "$NAME-keys" -v "$WORK/secrets:/secrets" \
    "$SERVICE_IMAGE" \
    hmpf-serve keys add --file /secrets/keys.yaml --name container-test --role admin \
    >"$WORK/key.out"
KEY=$(tail -n 1 "$WORK/key.out")
[ -n "$KEY" ] || fail "hmpf-serve keys add printed no key: $(cat "$WORK/key.out")"
# --network=host (this machine's podman networking): the service binds the published port on
# loopback itself; with a bridge network this is -p 127.0.0.1:$PORT:8000. No healthcheck
# timer (podman schedules it with systemd, absent here): it is run once by hand below.
"${RUN[@]}" -d --health-interval=disable --name "$NAME-service" \
    -e HMPF_HOST=127.0.0.1 -e HMPF_PORT="$PORT" \
    -e HMPF_KEYS_FILE=/run/secrets/hmpf_keys -e HMPF_SEQUENCE_KEY_FILE=/state/sequence-key \
    -v "$WORK/data:/data:ro" -v "$WORK/state:/state" \
    -v "$WORK/secrets/keys.yaml:/run/secrets/hmpf_keys:ro" \
    "$SERVICE_IMAGE" >/dev/null 2>"$WORK/run.err" \
    || { cat "$WORK/run.err" >&2; fail "podman run (service)"; }
URL=http://127.0.0.1:$PORT
ready=
for _ in $(seq 1 300); do
    if [ "$("$PODMAN" inspect --format '{{.State.Running}}' "$NAME-service" 2>/dev/null)" != true ]; then
        "$PODMAN" logs "$NAME-service" 2>&1 | tail -n 30 >&2
        fail "the service container stopped"
    fi
    if curl -fsS -o /dev/null "$URL/readyz" 2>/dev/null; then ready=1; break; fi
    sleep 1
done
[ -n "$ready" ] || { "$PODMAN" logs "$NAME-service" 2>&1 | tail -n 30 >&2; fail "/readyz not 200 in 300 s"; }
"$PODMAN" healthcheck run "$NAME-service" 2>/dev/null \
    || fail "the image's HEALTHCHECK does not pass on a ready service"
echo "HEALTHCHECK passes"
step_end

# ---- a night frame through the published port ------------------------------------------------
step_start "localize a night frame"
code=$(curl -sS -o "$WORK/noauth.json" -w '%{http_code}' -F "image=@$QUERY" "$URL/v1/localize")
[ "$code" = 401 ] || fail "without a key /v1/localize answered $code, not 401"
curl -fsS -H "X-API-Key: $KEY" -F "image=@$QUERY" "$URL/v1/localize" >"$WORK/answer.json" \
    || fail "POST /v1/localize failed"
MATCH=$(python3 - "$WORK/answer.json" "$EXPECT" <<'EOF'
import json
import sys

answer = json.load(open(sys.argv[1]))
match = answer.get("match")
if not match:
    sys.exit(f"no match in the answer: {json.dumps(answer)[:400]}")
expect = {int(v) for v in sys.argv[2].split()}
if match["reference_id"] not in expect:
    sys.exit(f"match {match['name']} (id {match['reference_id']}) not in {sorted(expect)}")
print(
    f"{match['name']} (reference {match['reference_id']}), score {match['score']}, "
    f"p_correct {match.get('p_correct')}, accepted {match.get('accepted')}"
)
EOF
) || fail "bad answer"
echo "answer: $MATCH"
step_end
# the served config, for RECORD (its digest names what was measured)
curl -fsS -H "X-API-Key: $KEY" "$URL/v1/index" >"$WORK/index.json" || fail "GET /v1/index failed"

echo
echo "== container-test passed in $(( $(date +%s) - T0 )) s"
echo "query $(basename "$QUERY") -> $MATCH"
report
if [ -n "${RECORD:-}" ]; then  # the run as a JSON record (docs/deployment-container.md's tables)
    python3 "$ROOT/docker/record.py" "$RECORD" "$WORK/answer.json" \
        "total=$(( $(date +%s) - T0 ))" "base_kept=$BASE_KEPT" "torch=$SERVICE_TORCH" \
        "indexer_mb=$(size_mb "$INDEXER_IMAGE")" "service_mb=$(size_mb "$SERVICE_IMAGE")" \
        "base_mb=$(size_mb "$BASE_IMAGE")" -- "${STEPS[@]}"
    echo "record: $RECORD"
fi
