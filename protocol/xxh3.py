"""XXH3-128 (seed 0, the default secret) in pure Python: the hash rmw_zenoh takes of an
entity's liveliness key expression to make its 16-byte GID (:func:`protocol.ros2.gid`).

This follows the published XXH3 specification (xxHash 0.8), all input lengths: 0–16, 17–128,
129–240 bytes and the striped long-input loop. It is slow (tens of microseconds for a token)
and called once per ROS 2 entity. ``tests/test_ros2.py`` checks it against the system's
libxxhash where one is installed.

>>> [hex(half) for half in xxh3_128_halves(b"")]  # low 64 bits, high 64 bits
['0x6001c324468d497f', '0x99aa06d3014798d8']
"""
from __future__ import annotations

import struct

_M64 = (1 << 64) - 1
_P32_1, _P32_2, _P32_3 = 0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D
_P64_1, _P64_2, _P64_3 = 0x9E3779B185EBCA87, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9
_P64_4, _P64_5 = 0x85EBCA77C2B2AE63, 0x27D4EB2F165667C5
_MX1, _MX2 = 0x165667919E3779F9, 0x9FB21C651E98DF25
_SECRET = bytes.fromhex(
    "b8fe6c3923a44bbe7c01812cf721ad1cded46de9839097db7240a4a4b7b3671f"
    "cb79e64eccc0e578825ad07dccff7221b8084674f743248ee03590e6813a264c"
    "3c2852bb91c300cb88d0658b1b532ea371644897a20df94e3819ef46a9deacd8"
    "a8fa763fe39c343ff9dcbbc7c70b4f1d8a51e04bcdb45931c89f7ec9d9787364"
    "eac5ac8334d3ebc3c581a0fffa1363eb170ddd51b7f0da49d316552629d4689e"
    "2b16be587d47a1fc8ff8b8d17ad031ce45cb3a8f95160428afd7fbcabb4b407e")
_STRIPE, _CONSUME, _SECRET_MIN = 64, 8, 136


def _u64(data: bytes, at: int) -> int:
    return struct.unpack_from("<Q", data, at)[0]


def _u32(data: bytes, at: int) -> int:
    return struct.unpack_from("<I", data, at)[0]


def _fold(a: int, b: int) -> int:
    """The 128-bit product of two 64-bit numbers, its halves xor-ed."""
    product = a * b
    return (product & _M64) ^ (product >> 64)


def _avalanche(h: int) -> int:
    h ^= h >> 37
    h = (h * _MX1) & _M64
    return h ^ (h >> 32)


def _xxh64_avalanche(h: int) -> int:
    h ^= h >> 33
    h = (h * _P64_2) & _M64
    h ^= h >> 29
    h = (h * _P64_3) & _M64
    return h ^ (h >> 32)


def _mix16(data: bytes, at: int, secret_at: int) -> int:
    return _fold(_u64(data, at) ^ _u64(_SECRET, secret_at),
                 _u64(data, at + 8) ^ _u64(_SECRET, secret_at + 8))


def _mix32(low: int, high: int, data: bytes, first: int, second: int,
           secret_at: int) -> tuple[int, int]:
    low = (low + _mix16(data, first, secret_at)) & _M64
    low ^= (_u64(data, second) + _u64(data, second + 8)) & _M64
    high = (high + _mix16(data, second, secret_at + 16)) & _M64
    high ^= (_u64(data, first) + _u64(data, first + 8)) & _M64
    return low, high


def _finish_mid(low: int, high: int, n: int) -> tuple[int, int]:
    """Final mixing shared by the 17–128 and 129–240 byte cases."""
    out_low = _avalanche((low + high) & _M64)
    out_high = ((low * _P64_1) + (high * _P64_4) + (n * _P64_2)) & _M64
    return out_low, (-_avalanche(out_high)) & _M64


def _upto16(data: bytes) -> tuple[int, int]:
    n = len(data)
    if n == 0:
        return (_xxh64_avalanche(_u64(_SECRET, 64) ^ _u64(_SECRET, 72)),
                _xxh64_avalanche(_u64(_SECRET, 80) ^ _u64(_SECRET, 88)))
    if n <= 3:
        combined = (data[0] << 16) | (data[n >> 1] << 24) | data[n - 1] | (n << 8)
        swapped = int.from_bytes(combined.to_bytes(4, "little"), "big")
        rotated = ((swapped << 13) | (swapped >> 19)) & 0xFFFFFFFF
        return (_xxh64_avalanche(combined ^ (_u32(_SECRET, 0) ^ _u32(_SECRET, 4))),
                _xxh64_avalanche(rotated ^ (_u32(_SECRET, 8) ^ _u32(_SECRET, 12))))
    if n <= 8:
        keyed = (_u32(data, 0) | (_u32(data, n - 4) << 32)) ^ (
            _u64(_SECRET, 16) ^ _u64(_SECRET, 24))
        product = keyed * ((_P64_1 + (n << 2)) & _M64)
        low, high = product & _M64, product >> 64
        high = (high + (low << 1)) & _M64
        low ^= high >> 3
        low ^= low >> 35
        low = (low * _MX2) & _M64
        low ^= low >> 28
        return low, _avalanche(high)
    flip_low = _u64(_SECRET, 32) ^ _u64(_SECRET, 40)
    flip_high = _u64(_SECRET, 48) ^ _u64(_SECRET, 56)
    first, last = _u64(data, 0), _u64(data, n - 8)
    product = (first ^ last ^ flip_low) * _P64_1
    low, high = product & _M64, product >> 64
    low = (low + ((n - 1) << 54)) & _M64
    last ^= flip_high
    high = (high + last + (last & 0xFFFFFFFF) * (_P32_2 - 1)) & _M64
    low ^= int.from_bytes(high.to_bytes(8, "little"), "big")
    product = low * _P64_2
    out_low, out_high = product & _M64, ((product >> 64) + high * _P64_2) & _M64
    return _avalanche(out_low), _avalanche(out_high)


def _upto128(data: bytes) -> tuple[int, int]:
    n = len(data)
    low, high = (n * _P64_1) & _M64, 0
    rounds = (n - 1) // 32  # 0..3 extra pairs, innermost first in the reference order
    for i in range(rounds, -1, -1):
        low, high = _mix32(low, high, data, 16 * i, n - 16 * (i + 1), 32 * i)
    return _finish_mid(low, high, n)


def _upto240(data: bytes) -> tuple[int, int]:
    n = len(data)
    low, high = (n * _P64_1) & _M64, 0
    for i in range(32, 160, 32):
        low, high = _mix32(low, high, data, i - 32, i - 16, i - 32)
    low, high = _avalanche(low), _avalanche(high)
    for i in range(160, n + 1, 32):
        low, high = _mix32(low, high, data, i - 32, i - 16, 3 + i - 160)
    low, high = _mix32(low, high, data, n - 16, n - 32, _SECRET_MIN - 17 - 16)
    return _finish_mid(low, high, n)


def _accumulate(acc: list[int], data: bytes, at: int, secret_at: int) -> None:
    for lane in range(8):
        value = _u64(data, at + 8 * lane)
        key = value ^ _u64(_SECRET, secret_at + 8 * lane)
        acc[lane ^ 1] = (acc[lane ^ 1] + value) & _M64
        acc[lane] = (acc[lane] + (key & 0xFFFFFFFF) * (key >> 32)) & _M64


def _scramble(acc: list[int]) -> None:
    secret_at = len(_SECRET) - _STRIPE
    for lane in range(8):
        value = acc[lane] ^ (acc[lane] >> 47) ^ _u64(_SECRET, secret_at + 8 * lane)
        acc[lane] = (value * _P32_1) & _M64


def _merge(acc: list[int], secret_at: int, start: int) -> int:
    total = start
    for i in range(4):
        total += _fold(acc[2 * i] ^ _u64(_SECRET, secret_at + 16 * i),
                       acc[2 * i + 1] ^ _u64(_SECRET, secret_at + 16 * i + 8))
    return _avalanche(total & _M64)


def _long(data: bytes) -> tuple[int, int]:
    n = len(data)
    acc = [_P32_3, _P64_1, _P64_2, _P64_3, _P64_4, _P32_2, _P64_5, _P32_1]
    per_block = (len(_SECRET) - _STRIPE) // _CONSUME
    block = _STRIPE * per_block
    blocks = (n - 1) // block
    for b in range(blocks):
        for s in range(per_block):
            _accumulate(acc, data, b * block + s * _STRIPE, s * _CONSUME)
        _scramble(acc)
    for s in range(((n - 1) - block * blocks) // _STRIPE):
        _accumulate(acc, data, blocks * block + s * _STRIPE, s * _CONSUME)
    _accumulate(acc, data, n - _STRIPE, len(_SECRET) - _STRIPE - 7)
    low = _merge(acc, 11, (n * _P64_1) & _M64)
    high = _merge(acc, len(_SECRET) - 64 - 11, ~(n * _P64_2) & _M64)
    return low, high


def xxh3_128_halves(data: bytes) -> tuple[int, int]:
    """XXH3-128 of ``data`` as its ``(low64, high64)`` halves."""
    data = bytes(data)
    n = len(data)
    if n <= 16:
        return _upto16(data)
    if n <= 128:
        return _upto128(data)
    if n <= 240:
        return _upto240(data)
    return _long(data)
