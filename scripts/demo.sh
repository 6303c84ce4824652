#!/usr/bin/env bash
# `make demo`: the streaming server end to end on this machine.
#   1. render a small synthetic capture with exact ground truth (voxfusion synth),
#   2. start `voxfusion serve` in the background (data in $OUT/data) and wait for /healthz,
#   3. create a session, print its live viewer link, and POST the frames one by one (binary frame messages,
#      proto/README.md),
#   4. finish the session and download the mesh and the trajectory with curl (the README's requests),
#   5. print the ATE against the ground truth (voxfusion eval) and the frame rate, stop the server.
#
# Environment overrides: DEMO_OUT (default demo-out), DEMO_PORT (8000), DEMO_FRAMES (40), DEMO_WIDTH (160),
# DEMO_HEIGHT (120), DEMO_MODE (offline: every frame tracked | realtime: the tracker takes the newest frame),
# DEMO_KEEP_SERVER=1 (keep the server up at the end, so the viewer link shows the finished scan; Ctrl-C stops it).
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${VENV:-.venv}
PY="$VENV/bin/python"
VF="$VENV/bin/voxfusion"
OUT=${DEMO_OUT:-demo-out}
PORT=${DEMO_PORT:-8000}
FRAMES=${DEMO_FRAMES:-40}
WIDTH=${DEMO_WIDTH:-160}
HEIGHT=${DEMO_HEIGHT:-120}
MODE=${DEMO_MODE:-offline}
URL="http://127.0.0.1:$PORT"

say() { printf '\033[1m[demo]\033[0m %s\n' "$*"; }

rm -rf "$OUT"
mkdir -p "$OUT"

say "rendering a synthetic capture: $FRAMES frames, ${WIDTH}x${HEIGHT}"
"$VF" synth "$OUT/capture" --frames "$FRAMES" --width "$WIDTH" --height "$HEIGHT" --seed 0 >/dev/null

say "starting voxfusion serve on $URL (log: $OUT/server.log)"
"$VF" serve --port "$PORT" --data-dir "$OUT/data" --device cpu --no-zenoh --log-level warning \
    >"$OUT/server.log" 2>&1 &
SERVER_PID=$!
stop_server() {
    if kill -0 "$SERVER_PID" 2>/dev/null; then
        kill -INT "$SERVER_PID" 2>/dev/null || true
        wait "$SERVER_PID" 2>/dev/null || true
    fi
}
trap stop_server EXIT

for _ in $(seq 1 240); do
    if curl -fsS "$URL/healthz" >/dev/null 2>&1; then break; fi
    if ! kill -0 "$SERVER_PID" 2>/dev/null; then say "the server exited:"; cat "$OUT/server.log"; exit 1; fi
    sleep 0.5
done
curl -fsS "$URL/healthz"; echo

say "creating a session ($MODE mode)"
curl -fsS -X POST "$URL/sessions" -H 'Content-Type: application/json' \
    -d "{\"name\": \"demo\", \"mode\": \"$MODE\"}" >"$OUT/session.json"
ID=$("$PY" -c 'import json, sys; print(json.load(open(sys.argv[1]))["id"])' "$OUT/session.json")
TOKEN=$("$PY" -c 'import json, sys; print(json.load(open(sys.argv[1]))["token"])' "$OUT/session.json")
say "session $ID"
VIEWER=$("$PY" -c 'import sys; from voxfusion.clients.http_client import viewer_url; print(viewer_url(*sys.argv[1:]))' \
    "$URL" "$ID" "$TOKEN")
say "live viewer (open it in a browser): $VIEWER"

say "streaming $FRAMES frames"
"$PY" - "$OUT/capture" "$URL" "$ID" "$TOKEN" <<'PYTHON'
"""POST every frame of a capture to a session as binary frame messages (one request per frame)."""
import sys
import time

import httpx

from voxfusion.core.datasets import open_capture
from voxfusion.proto import MEDIA_TYPE, encode_frame

capture_dir, url, sid, token = sys.argv[1:5]
capture = open_capture(capture_dir)
headers = {"Authorization": f"Bearer {token}", "Content-Type": MEDIA_TYPE}
t0 = time.perf_counter()
sent = waits = 0
with httpx.Client(base_url=url, timeout=60) as client:
    for i, frame in enumerate(capture.frames()):
        data = encode_frame(frame, seq=i, session=sid, depth_encoding="png16_mm", color_encoding="jpeg")
        while True:
            r = client.post(f"/sessions/{sid}/frames", content=data, headers=headers)
            if r.status_code != 429:  # queue full: wait as the server asks, then send the same frame again
                break
            waits += 1
            time.sleep(float(r.headers.get("Retry-After", "1")))
        r.raise_for_status()
        sent += 1
        # with waits, the rate is the engine's (the server's queue was full), not the upload's
        pace = f"the server's pace: its queue was full {waits} times" if waits else "nothing waited"
        print(f"\r  sent {sent}/{len(capture)} frames, {sent / (time.perf_counter() - t0):.1f} frames/s ({pace})",
              end="")
print()
PYTHON

say "finishing the session (remaining frames, final mapping, mesh, checkpoint)"
curl -fsS -X POST -H "Authorization: Bearer $TOKEN" "$URL/sessions/$ID/finish" >"$OUT/status.json"

say "downloading the mesh and the trajectory"
curl -fsS -H "Authorization: Bearer $TOKEN" -o "$OUT/mesh.ply" "$URL/sessions/$ID/mesh"
curl -fsS -H "Authorization: Bearer $TOKEN" -o "$OUT/trajectory.txt" "$URL/sessions/$ID/poses?format=tum"
ls -l "$OUT/mesh.ply" "$OUT/trajectory.txt"

say "accuracy against the ground truth"
"$VF" eval --traj "$OUT/trajectory.txt" --gt "$OUT/capture/groundtruth.txt" --json "$OUT/eval.json"
"$PY" - "$OUT/status.json" <<'PYTHON'
import json
import sys

st = json.load(open(sys.argv[1]))
print(f"[demo] session {st['id']}: {st['state']}, {st['frames_received']} frames received, "
      f"{st['frames_tracked']} tracked ({st.get('frames_lost', 0)} lost), {st['frames_dropped']} dropped by the "
      f"server, {st['keyframes']} keyframes, {st['voxels']} voxels; {st['fps']:.2f} frames/s tracked, mean pose latency {st['latency_ms']:.0f} ms")
PYTHON
say "outputs in $OUT/ (mesh.ply, trajectory.txt, eval.json; server data in $OUT/data)"
if [ "${DEMO_KEEP_SERVER:-0}" = 1 ]; then
    say "the server stays up: open the viewer link above to look at the scan; Ctrl-C stops it"
    wait "$SERVER_PID" || true
else
    say "to look at the scan in a browser, run DEMO_KEEP_SERVER=1 make demo and open the viewer link"
fi
