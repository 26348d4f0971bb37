"""A raw Modbus TCP server for tests: asyncio on 127.0.0.1, port chosen at run time, frames built
by hand (not by pymodbus, not by edge.codec), with programmable misbehaviour.

``RawServer(image)`` answers FC1-FC4 from ``image[(space, address)]`` (missing addresses ->
exception 2) and stores FC16 writes. ``server.misbehave`` may return the bytes of a whole reply
PDU (function code first), ``CLOSE`` to hang up, or None for the normal answer. Every request is
recorded as (device, function, address, count).
"""
from __future__ import annotations

import asyncio
import struct

CLOSE = object()
SPACE_OF = {1: "coil", 2: "discrete_input", 3: "holding", 4: "input"}


class RawServer:
    def __init__(self, image: dict | None = None) -> None:
        self.image: dict[tuple[str, int], int] = dict(image or {})
        self.requests: list[tuple[int, int, int, int]] = []
        self.times: list[float] = []      # event-loop time of each request
        self.connections = 0
        self.misbehave = None      # callable(device, fc, address, count, pdu) -> bytes|CLOSE|None
        self._server: asyncio.AbstractServer | None = None
        self._writers: set = set()

    async def __aenter__(self) -> RawServer:
        self._server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc) -> None:
        self._server.close()
        for w in list(self._writers):
            w.close()
        await self._server.wait_closed()

    def answer(self, device: int, pdu: bytes) -> bytes:
        """The normal reply PDU to ``pdu``."""
        fc = pdu[0]
        if fc in (1, 2, 3, 4):
            address, count = struct.unpack(">HH", pdu[1:5])
            space = SPACE_OF[fc]
            values = [self.image.get((space, a)) for a in range(address, address + count)]
            if any(v is None for v in values):
                return bytes([fc | 0x80, 2])
            if fc in (1, 2):
                data = bytearray((count + 7) // 8)
                for i, v in enumerate(values):
                    if v:
                        data[i // 8] |= 1 << (i % 8)
                return bytes([fc, len(data)]) + bytes(data)
            return bytes([fc, 2 * count]) + b"".join(struct.pack(">H", v) for v in values)
        if fc == 16:
            address, count, nbytes = struct.unpack(">HHB", pdu[1:6])
            words = struct.unpack(f">{count}H", pdu[6 : 6 + nbytes])
            for i, w in enumerate(words):
                self.image[("holding", address + i)] = w
            return struct.pack(">BHH", 16, address, count)
        return bytes([fc | 0x80, 1])

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        self._writers.add(writer)
        try:
            while True:
                head = await reader.readexactly(7)
                tid, _pid, length, device = struct.unpack(">HHHB", head)
                pdu = await reader.readexactly(length - 1)
                address, count = struct.unpack(">HH", pdu[1:5]) if len(pdu) >= 5 else (0, 0)
                self.requests.append((device, pdu[0], address, count))
                self.times.append(asyncio.get_running_loop().time())
                reply = self.misbehave(device, pdu[0], address, count, pdu) \
                    if self.misbehave else None
                if reply is CLOSE:
                    break
                if reply is None:
                    reply = self.answer(device, pdu)
                writer.write(struct.pack(">HHHB", tid, 0, len(reply) + 1, device) + reply)
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            self._writers.discard(writer)
            writer.close()
