"""A sensor-side publisher with the `eclipse-zenoh` package's zenoh.ext AdvancedPublisher.

usage: advanced_publisher.py ENDPOINT SETS.jsonl RATE STATUS_TIMEOUT_S

Connects to the daemon at ENDPOINT and declares an advanced publisher on
boltwatch/lab-frame/modal with a cache holding every set of SETS.jsonl, sample-miss
detection (heartbeat every 500 ms) and publisher detection, so a daemon restarted with an
AdvancedSubscriber (history, late-publisher detection, recovery) gets the sets published
while it was down. Waits (up to STATUS_TIMEOUT_S) for a subscriber, publishes every set
(one JSON payload per line) at RATE sets/s (0 = as fast as possible), as a sensor does:
with no pause when a restarted daemon reconnects (the daemon fetches what it missed), then
keeps the session and its cache alive, querying boltwatch/lab-frame/status every 200 ms,
until the daemon's last_set_time reaches the last set's time. Prints
{"published": N, "seconds": S, "confirmed": true/false}; exits with code 3 if the daemon
did not confirm within STATUS_TIMEOUT_S.
"""

import json
import sys
import time
from datetime import datetime

import zenoh
import zenoh.ext

KEY = "boltwatch/lab-frame/modal"
STATUS = "boltwatch/lab-frame/status"

endpoint, sets_path = sys.argv[1], sys.argv[2]
rate, status_timeout = float(sys.argv[3]), float(sys.argv[4])
sets = [line.strip() for line in open(sets_path) if line.strip()]


def parse_time(text):
    """An RFC 3339 time, truncated to the millisecond as the daemon writes its times."""
    t = datetime.fromisoformat(text.replace("Z", "+00:00"))
    return t.replace(microsecond=t.microsecond // 1000 * 1000)


last_time = parse_time(json.loads(sets[-1])["time"]) if sets else None

conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
conf.insert_json5("listen/endpoints", "[]")
conf.insert_json5("scouting/multicast/enabled", "false")
# Reconnect to a restarted daemon within 100 to 500 ms (Zenoh's default: 1 to 4 s).
conf.insert_json5(
    "connect/retry", "{period_init_ms: 100, period_max_ms: 500, period_increase_factor: 2}"
)
# Not needed with sample-miss detection (samples carry sequence numbers), but it gives the
# cached samples timestamps, so a subscriber's HistoryConfig(max_age=...) can filter them.
conf.insert_json5("timestamping/enabled", "true")


def confirmed(session):
    """Whether the daemon's status says it has taken the last set."""
    for reply in session.get(STATUS, timeout=1.0):
        if reply.ok is None:
            continue
        t = json.loads(reply.ok.payload.to_bytes()).get("last_set_time")
        if t is not None and last_time is not None and parse_time(t) >= last_time:
            return True
    return False


with zenoh.open(conf) as session:
    pub = zenoh.ext.declare_advanced_publisher(
        session,
        KEY,
        congestion_control=zenoh.CongestionControl.BLOCK,
        cache=zenoh.ext.CacheConfig(max(len(sets), 1)),
        sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=0.5),
        publisher_detection=True,
    )
    # AdvancedPublisher has no matching_status in Python: a plain publisher on the same key
    # (never used to put) tells whether a subscriber matches.
    probe = session.declare_publisher(KEY)
    deadline = time.monotonic() + status_timeout
    while not probe.matching_status.matching:
        if time.monotonic() > deadline:
            sys.exit(f"no subscriber on {KEY} after {status_timeout} s")
        time.sleep(0.05)
    probe.undeclare()

    start = time.monotonic()
    for k, payload in enumerate(sets):
        if rate > 0:
            delay = start + k / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        pub.put(payload.encode("utf-8"))
    seconds = time.monotonic() - start

    deadline = time.monotonic() + status_timeout
    done = last_time is None
    while not done:
        if time.monotonic() > deadline:
            break
        done = confirmed(session)
        if not done:
            time.sleep(0.2)
    print(json.dumps({"published": len(sets), "seconds": round(seconds, 3), "confirmed": done}))
    if not done:
        print(
            f"warning: the daemon did not take the last set within {status_timeout} s",
            file=sys.stderr,
        )
        sys.exit(3)
