#!/usr/bin/env python3
"""VMC with python-osc, an OSC implementation that is not posecast's (tests/vmc_python.rs).

    vmc_python.py send HOST PORT POSE_JSON [REPEAT]
        Sends POSE_JSON ({"root": [x, y, z, w], "bones": [[name, x, y, z, w], ...],
        "blend": {name: value}}, Unity frame) as VMC bundles, REPEAT times (default 30) at
        60 Hz: /VMC/Ext/OK, /VMC/Ext/T, /VMC/Ext/Root/Pos, one /VMC/Ext/Bone/Pos per bone,
        /VMC/Ext/Blend/Val per blend shape and /VMC/Ext/Blend/Apply. Every other bundle's bones
        go as single messages instead, the way some performers send them.

    vmc_python.py receive
        Binds 127.0.0.1 on a free UDP port, prints "PORT <n>", then one JSON line per datagram
        received: [[address, arg, ...], ...] (bundles flattened), until killed.

Also handy by hand: `send 127.0.0.1 39539 '{"bones": [["LeftUpperArm", 0, 0, 0.38, 0.92]]}'`
against `posecast --vmc-in 127.0.0.1:39539=avatar`.
"""

import json
import socket
import sys
import time

from pythonosc import osc_bundle_builder, osc_message_builder, osc_packet
from pythonosc.udp_client import SimpleUDPClient


def message(address, *args):
    m = osc_message_builder.OscMessageBuilder(address=address)
    for a in args:
        if isinstance(a, float):
            m.add_arg(a, arg_type="f")
        else:
            m.add_arg(a)
    return m.build()


def send(host, port, pose, repeat):
    client = SimpleUDPClient(host, port)
    root = [float(c) for c in pose.get("root", [0, 0, 0, 1])]
    bones = pose.get("bones", [])
    blend = pose.get("blend", {})
    start = time.monotonic()
    for i in range(repeat):
        b = osc_bundle_builder.OscBundleBuilder(osc_bundle_builder.IMMEDIATELY)
        b.add_content(message("/VMC/Ext/OK", 1))
        b.add_content(message("/VMC/Ext/T", float(time.monotonic() - start)))
        b.add_content(message("/VMC/Ext/Root/Pos", "root", 0.0, 0.0, 0.0, *root))
        singles = i % 2 == 1
        for name, x, y, z, w in bones:
            m = message("/VMC/Ext/Bone/Pos", name, 0.0, 0.0, 0.0, float(x), float(y), float(z), float(w))
            if singles:
                client.send(m)
            else:
                b.add_content(m)
        for name, value in blend.items():
            b.add_content(message("/VMC/Ext/Blend/Val", name, float(value)))
        b.add_content(message("/VMC/Ext/Blend/Apply"))
        client.send(b.build())
        time.sleep(1 / 60)


def receive():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    print("PORT", s.getsockname()[1], flush=True)
    while True:
        data, _ = s.recvfrom(65536)
        packet = osc_packet.OscPacket(data)
        out = [[t.message.address, *t.message.params] for t in packet.messages]
        print(json.dumps(out), flush=True)


def main(argv):
    if len(argv) >= 4 and argv[0] == "send":
        repeat = int(argv[4]) if len(argv) > 4 else 30
        send(argv[1], int(argv[2]), json.loads(argv[3]), repeat)
    elif argv[:1] == ["receive"]:
        receive()
    else:
        print(__doc__, file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
