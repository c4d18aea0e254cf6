"""The master's side of XCP on this bench, on pyxcp: what ``python -m hil xcp`` and the tests
share."""

from __future__ import annotations

from calib.a2l import MAX_BS, MAX_CTO


def push(x, address: int, data: bytes) -> None:
    """Write ``data`` at ``address`` in master block mode: blocks of MAX_BS frames (240 bytes,
    whole doubles), each a DOWNLOAD and its DOWNLOAD_NEXTs, one response per block. (pyxcp
    0.29.20's ``Master.push`` sends the tail of a 7 to 11 byte block as a second DOWNLOAD,
    which the slave refuses as out of sequence: this uses its DOWNLOAD and DOWNLOAD_NEXT.)"""
    step = MAX_CTO - 2
    block = MAX_BS * step
    x.setMta(address)
    for off in range(0, len(data), block):
        chunk = data[off:off + block]
        if len(chunk) <= step:
            x.download(chunk)
            continue
        x.download(chunk[:step], block_mode_length=len(chunk))
        rest = chunk[step:]
        while rest:
            part, rest = rest[:step], rest[step:]
            x.downloadNext(part, len(part) + len(rest), last=not rest)
