"""A Foxglove WebSocket client as the Foxglove app speaks the protocol (subprotocol
``foxglove.sdk.v1``): JSON ``serverInfo`` and ``advertise`` from the server, ``subscribe``
from the client, binary ``messageData`` frames (opcode 1, subscription id u32 LE, log time
u64 LE, payload); payloads decoded with protobuf from the schema the channel advertised
(a base64 FileDescriptorSet), as the app does. Nothing of cubeloc's or the SDK's is used."""

from __future__ import annotations

import base64
import json
import struct
import time

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

SUBPROTOCOL = "foxglove.sdk.v1"


def message_class(schema_name: str, schema: bytes):
    """The protobuf class of ``schema_name`` from a serialized FileDescriptorSet."""
    files = descriptor_pb2.FileDescriptorSet.FromString(schema)
    pool = descriptor_pool.DescriptorPool()
    for proto in files.file:
        pool.Add(proto)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


class FoxgloveClient:
    def __init__(self, port: int, host: str = "127.0.0.1", timeout_s: float = 10.0) -> None:
        self.ws = connect(f"ws://{host}:{port}", subprotocols=[SUBPROTOCOL], open_timeout=timeout_s,
                          max_size=None).__enter__()  # closed by close()
        self.server_info: dict | None = None
        self.channels: dict[str, dict] = {}  # topic -> advertised channel
        self._subscriptions: dict[int, dict] = {}  # subscription id -> channel
        self._classes: dict[str, type] = {}
        self._next_id = 1

    def close(self) -> None:
        self.ws.close()

    def __enter__(self) -> FoxgloveClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _handle_text(self, text: str) -> None:
        message = json.loads(text)
        if message["op"] == "serverInfo":
            self.server_info = message
        elif message["op"] == "advertise":
            for channel in message["channels"]:
                self.channels[channel["topic"]] = channel
        elif message["op"] == "unadvertise":
            gone = set(message["channelIds"])
            self.channels = {t: c for t, c in self.channels.items() if c["id"] not in gone}

    def wait_for_topics(self, topics, timeout_s: float = 10.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not set(topics) <= set(self.channels):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"topics not advertised: {sorted(set(topics) - set(self.channels))}")
            data = self.ws.recv(timeout=remaining)
            if isinstance(data, str):
                self._handle_text(data)

    def subscribe(self, *topics: str) -> None:
        subscriptions = []
        for topic in topics:
            channel = self.channels[topic]
            subscriptions.append({"id": self._next_id, "channelId": channel["id"]})
            self._subscriptions[self._next_id] = channel
            self._next_id += 1
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))

    def decode(self, channel: dict, payload: bytes):
        name = channel["schemaName"]
        if name not in self._classes:
            self._classes[name] = message_class(name, base64.b64decode(channel["schema"]))
        return self._classes[name].FromString(payload)

    def messages(self, want: dict[str, int], timeout_s: float = 20.0) -> dict[str, list]:
        """Receive until each topic in ``want`` has that many messages: topic -> [(log
        time ns, decoded message)]."""
        got: dict[str, list] = {topic: [] for topic in want}
        deadline = time.monotonic() + timeout_s
        while any(len(got[t]) < n for t, n in want.items()):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                short = {t: len(got[t]) for t, n in want.items() if len(got[t]) < n}
                raise TimeoutError(f"too few messages within {timeout_s} s: {short}")
            data = self.ws.recv(timeout=remaining)
            if isinstance(data, str):
                self._handle_text(data)
                continue
            if data[0] != 1:  # not messageData (time, service responses...)
                continue
            subscription, log_time = struct.unpack_from("<IQ", data, 1)
            channel = self._subscriptions[subscription]
            if channel["topic"] in got:
                got[channel["topic"]].append((log_time, self.decode(channel, data[13:])))
        return got


if __name__ == "__main__":  # python tests/foxglove_client.py PORT: the bench's viewer (bench/foxglove.py)
    import sys

    with FoxgloveClient(int(sys.argv[1])) as viewer:
        viewer.wait_for_topics(["/camera/image", "/pose"])
        topics = sorted(viewer.channels)
        viewer.subscribe(*topics)
        print("subscribed", flush=True)
        counts = dict.fromkeys(topics, 0)
        stop_at = time.monotonic() + float(sys.argv[2])
        while time.monotonic() < stop_at:
            try:
                data = viewer.ws.recv(timeout=max(0.01, stop_at - time.monotonic()))
            except (TimeoutError, ConnectionClosed):  # the bench stopped the daemon first
                break
            if isinstance(data, bytes) and data[0] == 1:
                counts[viewer._subscriptions[struct.unpack_from("<I", data, 1)[0]]["topic"]] += 1
        print(json.dumps(counts), flush=True)
