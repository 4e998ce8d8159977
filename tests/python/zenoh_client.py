"""A boltwatch client with the `eclipse-zenoh` package (used by tests/suite/daemon.rs).

usage: zenoh_client.py ENDPOINT SETS.jsonl N_ALERTS

Connects to the daemon at ENDPOINT, subscribes to lab-frame's stiffness and alerts,
publishes every modal set of SETS.jsonl (one JSON payload per line) on
boltwatch/lab-frame/modal, waits for one estimate per set and N_ALERTS alerts, queries
boltwatch/lab-frame/status, and prints {"stiffness": [...], "alerts": [...], "status": {...}}.
"""

import json
import sys
import threading
import time

import zenoh

endpoint, sets_path, n_alerts = sys.argv[1], sys.argv[2], int(sys.argv[3])
sets = [line for line in open(sets_path) if line.strip()]

conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
conf.insert_json5("listen/endpoints", "[]")
conf.insert_json5("scouting/multicast/enabled", "false")

got = {"stiffness": [], "alerts": []}
lock = threading.Lock()


def keep(kind):
    def cb(sample):
        with lock:
            got[kind].append(json.loads(sample.payload.to_bytes()))

    return cb


with zenoh.open(conf) as session:
    subs = [
        session.declare_subscriber(f"boltwatch/lab-frame/{kind}", keep(kind))
        for kind in ("stiffness", "alerts")
    ]
    pub = session.declare_publisher(
        "boltwatch/lab-frame/modal", congestion_control=zenoh.CongestionControl.BLOCK
    )
    deadline = time.time() + 30
    while not pub.matching_status.matching:
        if time.time() > deadline:
            sys.exit("no subscriber on boltwatch/lab-frame/modal after 30 s")
        time.sleep(0.05)
    for payload in sets:
        pub.put(payload.strip().encode())
    deadline = time.time() + 120
    while True:
        with lock:
            done = len(got["stiffness"]) >= len(sets) and len(got["alerts"]) >= n_alerts
        if done:
            break
        if time.time() > deadline:
            sys.exit(
                f"timed out: {len(got['stiffness'])} estimates of {len(sets)}, "
                f"{len(got['alerts'])} alerts of {n_alerts}"
            )
        time.sleep(0.05)
    status = None
    for reply in session.get("boltwatch/lab-frame/status"):
        if reply.ok is not None:
            status = json.loads(reply.ok.payload.to_bytes())
    if status is None:
        sys.exit("no status reply")
    with lock:
        print(json.dumps({"stiffness": got["stiffness"], "alerts": got["alerts"], "status": status}))
