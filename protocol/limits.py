"""Every bound the protocol puts on what it accepts (design §8 limits), in one place.

The codec (:mod:`protocol.messages`) refuses a payload larger than :data:`MAX_PAYLOAD_BYTES`
before decoding it, then decodes with msgpack's own length bounds and checks the nesting
depth; the Zenoh configs the project writes may use :data:`MAX_PAYLOAD_BYTES` to size their
``max_message_size``. The largest real message (a ``Sensing`` with every optional vector) is
about 200 bytes, so the bounds leave ample room and still make every refusal cheap.

The observers' payloads (:mod:`protocol.view`: the map and the tick chunks on ``world/view/**``)
are larger, so they have bounds of their own (:data:`MAX_VIEW_BYTES`,
:data:`VIEW_MSGPACK_BOUNDS`), decoded by the same function as the messages.
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
"""Longest name (an estimator's, as its policy calls itself in every observation)."""

MAX_RUN_ID = 64
"""Longest run id (a chunk of every key expression, and a folder name)."""

NAME_PATTERN = re.compile(rf"[A-Za-z][A-Za-z0-9_.:+-]{{0,{MAX_NAME - 1}}}")
"""A name starts with a letter and uses a small safe alphabet: it can never be read as a
spreadsheet formula nor carry a separator, quote, space or control character."""

NAME_RULE = f"1-{MAX_NAME} characters of [A-Za-z0-9_.:+-] starting with a letter"
""":data:`NAME_PATTERN` in words, for error messages."""

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


# --- observer payloads (protocol.view) ---------------------------------------------------------

MAX_VIEW_BYTES = 32 * 1024
"""Largest view payload (the map, or one tick chunk), checked before decoding and on encoding
(a map of 4,096 cells is about 16.5 KB, a chunk of 200 rows at most 19.2 KB)."""

MAP_CELLS = 4096
"""Most cells of the view map's height grid (``ny * nx``)."""

ROWS_PER_CHUNK = 200
"""Most agent rows in one tick chunk: a tick of more agents is sent as several chunks."""

MAX_VIEW_TEXT = 256
"""Longest text field of the view map (run id, surface, estimator, dictionary, mode), in
characters."""

MAX_VIEW_DEPTH = 3
"""Deepest nesting in a view payload: the payload map (1) holding the rows (2) of values (3)."""

MAX_VIEW_FIELDS = 32
"""Most entries in a view payload's map (the map payload has 17)."""

VIEW_MSGPACK_BOUNDS = {
    "max_str_len": 4 * MAX_VIEW_TEXT,
    "max_bin_len": 4 * MAP_CELLS,  # the map's heights travel as 32-bit floats
    # the longest list on the wire is a chunk's rows (a row has 13 values, the box 4); msgpack
    # allocates a list's claimed length before reading it, at each of up to 1024 levels
    "max_array_len": ROWS_PER_CHUNK,
    "max_map_len": MAX_VIEW_FIELDS,
    "max_ext_len": 0,
}
"""Keyword arguments of ``msgpack.unpackb`` for view payloads (like :data:`MSGPACK_BOUNDS`)."""
