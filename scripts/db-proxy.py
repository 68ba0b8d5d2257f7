#!/usr/bin/env python3
"""A TCP proxy for database outage drills (loopback only).

Usage: db-proxy.py LISTEN_PORT UPSTREAM_PORT
Signals: SIGUSR1 toggles "frozen" (connections stay open, no byte moves: a stalled
database); SIGUSR2 toggles "refusing" (every connection is closed and new ones are
refused at once: a database that is down). Exits on SIGTERM.
"""
import selectors, signal, socket, sys

listen_port, upstream_port = int(sys.argv[1]), int(sys.argv[2])
state = {"frozen": False, "refusing": False}
pairs = {}
sel = selectors.DefaultSelector()

def close_all():
    for s in list(pairs):
        try: sel.unregister(s)
        except Exception: pass
        s.close()
    pairs.clear()

def toggle(key):
    state[key] = not state[key]
    print(f"proxy: {key} = {state[key]}", flush=True)
    if key == "refusing" and state[key]:
        close_all()

signal.signal(signal.SIGUSR1, lambda *_: toggle("frozen"))
signal.signal(signal.SIGUSR2, lambda *_: toggle("refusing"))
server = socket.socket(); server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
server.bind(("127.0.0.1", listen_port)); server.listen(128)
sel.register(server, selectors.EVENT_READ)
while True:
    try:
        events = sel.select(timeout=0.05)
    except InterruptedError:
        continue
    for key, _ in events:
        s = key.fileobj
        if s is server:
            client, _ = server.accept()
            if state["refusing"]:
                client.close(); continue
            up = socket.create_connection(("127.0.0.1", upstream_port))
            pairs[client], pairs[up] = up, client
            sel.register(client, selectors.EVENT_READ); sel.register(up, selectors.EVENT_READ)
        elif not state["frozen"] and s in pairs:
            try:
                data = s.recv(65536)
            except OSError:
                data = b""
            peer = pairs.get(s)
            if not data or peer is None:
                for x in (s, peer):
                    if x is not None and x in pairs:
                        sel.unregister(x); pairs.pop(x, None); x.close()
                continue
            peer.sendall(data)
