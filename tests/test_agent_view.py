"""agent.view: a WebSocket client speaking Foxglove's protocol receives the fleet's channels.

The client is written from the Foxglove WebSocket protocol (subprotocol ``foxglove.sdk.v1``:
``advertise``, ``subscribe``, binary ``messageData`` = opcode 1, subscription id u32, log time
u64, payload) with the ``websockets`` library, and decodes the grid with Google's protobuf
runtime from the schema the server advertises: no code of the view's is reused.
"""

from __future__ import annotations

import asyncio
import base64
import json
import struct

import numpy as np
import pytest

from pgvd.io import read_map
from protocol.ros2.occupancy import Placement

pytest.importorskip("foxglove")
websockets = pytest.importorskip("websockets")
descriptor_pb2 = pytest.importorskip("google.protobuf.descriptor_pb2")

from google.protobuf import descriptor_pool, message_factory  # noqa: E402

from agent.view import GRID_TOPIC, LINKS_TOPIC, TF_TOPIC, FoxgloveView, parse_endpoint  # noqa: E402

# The message classes of every decoded schema, kept for the whole session.  protobuf's upb
# runtime (4.22 at least) builds a nested message's class (the grid's Pose) on demand and does
# not keep it alive; once the garbage collector frees it, reading that field segfaults
# (protocolbuffers/protobuf#12047).  The lowest-versions CI job crashed here, at FromString,
# in runs where a collection happened in between; a gc.collect() there crashes it every time.
_CLASSES: list[dict] = []


def _decoder(channel: dict):
    """A protobuf message class for an advertised channel, from its FileDescriptorSet."""
    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for proto in files.file:
        pool.Add(proto)
    classes = message_factory.GetMessageClassesForFiles([f.name for f in files.file], pool)
    _CLASSES.append(classes)
    return classes[channel["schemaName"]]


async def _receive(port: int, show) -> dict[str, bytes]:
    """Subscribe to every channel, let ``show`` publish, return each topic's payload."""
    uri = f"ws://127.0.0.1:{port}"
    async with websockets.connect(uri, subprotocols=["foxglove.sdk.v1"]) as ws:
        channels: dict[int, dict] = {}
        while len(channels) < 3:
            msg = json.loads(await asyncio.wait_for(ws.recv(), 5))
            if msg["op"] == "advertise":
                channels.update({c["id"]: c for c in msg["channels"]})
        subs = [{"id": i, "channelId": cid} for i, cid in enumerate(channels)]
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        await asyncio.sleep(0.3)  # the server handles the subscription before data flows
        show()
        payloads: dict[str, bytes] = {}
        while len(payloads) < 3:
            frame = await asyncio.wait_for(ws.recv(), 5)
            if isinstance(frame, bytes) and frame[0] == 1:
                sub, _ = struct.unpack_from("<IQ", frame, 1)
                channel = channels[subs[sub]["channelId"]]
                payloads[channel["topic"]] = (channel, frame[13:])
        return payloads


def test_a_foxglove_client_receives_the_global_map_tf_and_links(shared) -> None:
    grid = read_map(shared / "maps" / "intel" / "intel.yaml")
    view = FoxgloveView("127.0.0.1", 0)
    placements = [
        Placement("world", "r1/map", 0.0, 0.0, 0.0),
        Placement("world", "r2/map", 4.0, -2.0, 0.3),
    ]
    links = [{"a": "r1", "b": "r2", "state": "accepted", "score": 0.97}]
    try:
        payloads = asyncio.run(
            _receive(view.port, lambda: view.show(grid, placements, links, 5 * 10**9))
        )
    finally:
        view.close()
    channel, data = payloads[GRID_TOPIC]
    assert channel["schemaName"] == "foxglove.Grid"
    msg = _decoder(channel).FromString(data)
    h, w = grid.shape
    assert msg.column_count == w and msg.row_stride == w and len(msg.data) == h * w
    assert msg.cell_size.x == pytest.approx(grid.resolution) and msg.frame_id == "world"
    assert (msg.pose.position.x, msg.pose.position.y) == pytest.approx(grid.origin[:2])
    cells = np.frombuffer(msg.data, dtype=np.int8).reshape(h, w)
    # Row 0 is the map's lowest row; unknown stays -1 and walls are 100.
    assert np.array_equal(cells[::-1] == -1, grid.logodds == 0)
    assert np.array_equal(cells[::-1] == 100, grid.probability() > 0.65)
    channel, data = payloads[TF_TOPIC]
    tf = _decoder(channel).FromString(data)
    assert [(t.parent_frame_id, t.child_frame_id) for t in tf.transforms] == [
        ("world", "r1/map"),
        ("world", "r2/map"),
    ]
    assert tf.transforms[1].translation.x == 4.0
    _, data = payloads[LINKS_TOPIC]
    assert json.loads(data) == {"links": links}


@pytest.mark.parametrize("text", ["8765", "host:", ":8765", "host:port", "host:70000"])
def test_bad_endpoints_get_one_clear_error(text: str) -> None:
    with pytest.raises(ValueError, match="HOST:PORT"):
        parse_endpoint(text)


def test_endpoints_parse() -> None:
    assert parse_endpoint("127.0.0.1:8765") == ("127.0.0.1", 8765)
    assert parse_endpoint("::1:0") == ("::1", 0)
