"""A Zenoh router in this process (zenohd's role) for tests: listens on argv[1], prints
`ready`, runs until killed."""

import json
import sys
import time

import zenoh

cfg = zenoh.Config()
cfg.insert_json5("mode", json.dumps("router"))
cfg.insert_json5("scouting/multicast/enabled", "false")
cfg.insert_json5("listen/endpoints", json.dumps([sys.argv[1]]))
session = zenoh.open(cfg)
print("ready", flush=True)
while True:
    time.sleep(3600)
