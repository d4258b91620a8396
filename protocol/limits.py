"""Every bound the protocol puts on what it accepts (SPEC §8 limits), in one place.

The codec (:mod:`protocol.messages`) refuses a payload larger than :data:`MAX_PAYLOAD_BYTES`
before decoding it, then decodes with msgpack's own length bounds and checks the nesting
depth; the Zenoh configs the project writes may use :data:`MAX_PAYLOAD_BYTES` to size their
``max_message_size``. The largest real message (a ``Sensing`` with every optional vector) is
about 200 bytes, so the bounds leave ample room and still make every refusal cheap.
"""
from __future__ import annotations

import re

MAX_PAYLOAD_BYTES = 4096
"""Largest request or sample accepted, checked before decoding (no real message is near it)."""

MAX_DEPTH = 2
"""Deepest nesting of containers: the message map (1) holding lists of numbers (2)."""

MAX_FIELDS = 16
"""Most entries in a message map (the largest message, ``Sensing``, has 10 with ``v``/``type``)."""

MAX_VECTOR = 64
"""Longest list of numbers in a message (a measurement or prediction vector)."""

MAX_TEXT = 512
"""Longest free-text field (an error, a reason, a results path), in characters."""

MAX_STR_BYTES = 4 * MAX_TEXT
"""msgpack bound on one string, in UTF-8 bytes (the character bound is checked after)."""

MAX_NAME = 64
"""Longest name (an estimator's)."""

NAME_PATTERN = re.compile(r"[A-Za-z][A-Za-z0-9_.:+-]{0,%d}" % (MAX_NAME - 1))
"""A name starts with a letter and uses a small safe alphabet: it can never be read as a
spreadsheet formula nor carry a separator, quote, space or control character."""

MAX_TICK = 10_000_000
"""Largest tick number (and count) a message may carry."""

MSGPACK_BOUNDS = {
    "max_str_len": MAX_STR_BYTES,
    "max_bin_len": 0,  # no message has a binary field
    "max_array_len": MAX_VECTOR,
    "max_map_len": MAX_FIELDS,
    "max_ext_len": 0,  # nor an extension type
}
"""Keyword arguments of ``msgpack.unpackb`` that bound every length it will allocate."""
