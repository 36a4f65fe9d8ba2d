"""Shared pieces of the reader fuzz tests.

A bounded hypothesis profile, file corruptors and the "clean outcome" check (valid seed files
are in fuzz_seeds.py).

Every fuzz test writes a valid file, corrupts it with one to three random edits and reads it
back. The outcome must be clean (:func:`read_clean`): either a ValueError (or
:class:`DatasetError`) whose message names the file, or a result the test then checks for
validity. A guard fails the example on a hang (an interval timer) and on an allocation that
grows with a corrupt count rather than with the file (tracemalloc peak).
"""
from __future__ import annotations

import contextlib
import json
import math
import re
import signal
import struct
import tracemalloc
from typing import Any, Callable, List, Sequence, Tuple

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from icomma_plugin.io.datasets import DatasetError

HANG_S = 10.0  # per example; the seed files are read in milliseconds
PEAK_BYTES = 64 << 20  # every seed file is a few KiB; 64 MiB means a count was trusted


def fuzz_settings(max_examples: int) -> settings:
    """The fuzz profile with ``max_examples`` examples.

    Reproducible and database-less: every run tries the same examples and no example database
    is written (tests/conftest.py moves hypothesis's other caches out of the repository).
    No deadline, which would time examples on a shared machine; a hang is caught by HANG_S.
    """
    return settings(max_examples=max_examples, deadline=None, derandomize=True, database=None,
                    print_blob=False,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


class Hang(BaseException):
    """A reader ran past :data:`HANG_S` on a few-KiB file.

    A BaseException, so that a reader's ``except Exception`` cannot swallow it.
    """


@contextlib.contextmanager
def _guard():
    def alarm(signum, frame):
        raise Hang(f"reader still running after {HANG_S} s")

    old = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, HANG_S)
    tracemalloc.start()
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert peak < PEAK_BYTES, f"reader allocated {peak / 2**20:.0f} MiB on a small file"


def read_clean(call: Callable[[], Any], names: Sequence[str]) -> Tuple[Any, Exception]:
    """Run ``call()`` under the hang/memory guard; return ``(result, None)`` or ``(None, error)``.

    Fails unless the call returns or raises a plain ValueError / DatasetError whose message
    contains one of ``names`` (the file, or the folder for folder-level errors). ValueError
    subclasses that signal an unhandled decode (UnicodeDecodeError, json.JSONDecodeError) fail.
    """
    with _guard():
        try:
            return call(), None
        except Exception as e:  # noqa: BLE001 - the point is to see every escaping type
            err = e
    assert type(err) is ValueError or isinstance(err, DatasetError), (
        f"unclean error {type(err).__name__}: {err}")
    msg = str(err)
    assert any(n in msg for n in names), f"error does not name the file ({names}): {msg}"
    # Errors may quote a corrupt line or token, but never dump a whole file.
    assert len(msg) < 10_000, f"error message of {len(msg)} characters"
    return None, err


# ----------------------------------------------------------------------------- interesting values

COUNTS = [0, 1, 2, 3, 7, 255, 2**31 - 1, 2**31, 2**32 - 1, 2**32, 10**12, 2**63 - 1, 2**64 - 1]
INT32S = [0, 1, -1, 2, 99, 2**31 - 1, -(2**31)]
FLOATS = [math.nan, math.inf, -math.inf, 0.0, -0.0, 1.0, -1.0, 1e-320, 1e38, -1e38, 1e308,
          -1e308, 1e6]
TOKENS = ["nan", "NaN", "inf", "-inf", "1e999", "-1e999", "1e-400", "0", "-0", "-1", "1", "2",
          "255", "256", "4294967296", "18446744073709551616", "9" * 25, "9" * 400, "9" * 5000,
          "0x10", "1_0", "x", "", "\u0661", "\x00", "\u00e9", "True", "None", "[", "(", "'",
          "\\", "{", "]"]
JSON_VALUES = [math.nan, math.inf, -math.inf, 1e308, -1.0, 0, 1, 0.5, 10**30, 10**400, 2**64,
               "r_0", "", None, True, False, [], {}, [0.0, 0.0], [[1, 0, 0], [0, 1, 0]],
               [[[[[[[[0]]]]]]]], {"id": 0}]
JSON_RAW = ["[" * 100_000, "1" + "0" * 5000, "1e999", "-Infinity", "NaN", "\"\\ud800\"", "{",
            "[1,]", "\x00"]


def pack(fmt: str, v) -> bytes:
    """``v`` packed little-endian as ``fmt``.

    An int out of range wraps, a float too large for ``f`` becomes Inf.
    """
    if fmt in "df":
        try:
            return struct.pack("<" + fmt, v)
        except OverflowError:
            return struct.pack("<" + fmt, math.copysign(math.inf, v))
    return struct.pack("<" + fmt.upper(), v % 2 ** (8 * struct.calcsize(fmt)))


def _value_for(fmt: str):
    if fmt in ("Q", "q"):
        return st.one_of(st.sampled_from(COUNTS), st.integers(0, 2**64 - 1))
    if fmt in ("i", "I"):
        return st.one_of(st.sampled_from(INT32S), st.integers(-(2**31), 2**31 - 1))
    if fmt in ("d", "f"):
        return st.one_of(st.sampled_from(FLOATS), st.floats(allow_nan=True, width=64))
    return st.integers(0, 255)  # "B"


# ----------------------------------------------------------------------------- byte corruptors

@st.composite
def _byte_edit(draw, data: bytes, slots: Sequence[Tuple[int, str]]) -> bytes:
    n = len(data)
    kinds = ["truncate", "flip", "overwrite", "insert", "delete", "duplicate"]
    if slots:
        kinds += ["slot", "slot"]  # structure-aware edits are the most telling: weight them
    kind = draw(st.sampled_from(kinds))
    if n == 0:
        return draw(st.binary(max_size=16))
    pos = draw(st.integers(0, n - 1))
    if kind == "truncate":
        return data[:pos]
    if kind == "flip":
        return data[:pos] + bytes([data[pos] ^ (1 << draw(st.integers(0, 7)))]) + data[pos + 1:]
    if kind == "overwrite":
        junk = draw(st.binary(min_size=1, max_size=16))
        return data[:pos] + junk + data[pos + len(junk):]
    if kind == "insert":
        return data[:pos] + draw(st.binary(min_size=1, max_size=16)) + data[pos:]
    if kind == "delete":
        return data[:pos] + data[pos + draw(st.integers(1, 64)):]
    if kind == "duplicate":
        end = min(n, pos + draw(st.integers(1, 64)))
        return data[:end] + data[pos:end] + data[end:]
    off, fmt = draw(st.sampled_from(list(slots)))
    raw = pack(fmt, draw(_value_for(fmt)))
    return data[:off] + raw + data[off + len(raw):]


@st.composite
def corrupt_bytes(draw, data: bytes, slots: Sequence[Tuple[int, str]] = ()) -> bytes:
    """``data`` after 1..3 random edits.

    Truncation, bit flips, junk, cut/duplicated runs, or an interesting value (huge count, NaN, ...)
    packed into a known field ``(offset, struct fmt)``. Slot offsets refer to the original bytes;
    later edits may shift them, which is fine.
    """
    for _ in range(draw(st.integers(1, 3))):
        data = draw(_byte_edit(data, slots))
    return data


_TOKEN_RE = re.compile(r"\S+")


@st.composite
def corrupt_text(draw, text: str) -> bytes:
    """``text`` after 1..3 token- or line-level edits, encoded.

    NaN, huge numbers, junk tokens, deleted, duplicated or swapped lines, truncation; sometimes
    byte-corrupted on top.
    """
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["token", "token", "token", "drop_line", "dup_line",
                                     "swap_lines", "truncate", "junk"]))
        lines = text.split("\n")
        if kind == "token":
            spans = [m.span() for m in _TOKEN_RE.finditer(text)]
            if spans:
                a, b = draw(st.sampled_from(spans))
                new = draw(st.one_of(st.sampled_from(TOKENS), st.text(max_size=8)))
                text = text[:a] + new + text[b:]
        elif kind == "drop_line" and lines:
            del lines[draw(st.integers(0, len(lines) - 1))]
            text = "\n".join(lines)
        elif kind == "dup_line" and lines:
            i = draw(st.integers(0, len(lines) - 1))
            lines.insert(i, lines[i])
            text = "\n".join(lines)
        elif kind == "swap_lines" and len(lines) > 1:
            i, j = draw(st.integers(0, len(lines) - 1)), draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
            text = "\n".join(lines)
        elif kind == "truncate" and text:
            text = text[:draw(st.integers(0, len(text) - 1))]
        elif kind == "junk":
            pos = draw(st.integers(0, len(text)))
            text = text[:pos] + draw(st.text(min_size=1, max_size=20)) + text[pos:]
    data = text.encode("utf-8", "surrogatepass")
    if draw(st.integers(0, 3)) == 0:
        data = draw(corrupt_bytes(data))
    return data


def json_paths(obj, prefix=()) -> List[tuple]:
    """Key/index paths of every node of a JSON value, the root ``()`` first."""
    out = [prefix]
    if isinstance(obj, dict):
        for k, v in obj.items():
            out += json_paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out += json_paths(v, prefix + (i,))
    return out


@st.composite
def corrupt_json(draw, obj) -> bytes:
    """A JSON document after 1..3 structural or raw-text edits.

    Structural: a node replaced by NaN, a huge number, a wrong type, deep nesting; a key or element
    deleted or duplicated.
    """
    obj = json.loads(json.dumps(obj))
    raw_inject = None
    for _ in range(draw(st.integers(1, 3))):
        paths = json_paths(obj)
        path = draw(st.sampled_from(paths))
        kind = draw(st.sampled_from(["replace", "replace", "delete", "duplicate", "raw"]))
        if kind == "raw":
            raw_inject = draw(st.sampled_from(JSON_RAW))
            continue
        new = json.loads(json.dumps(draw(st.sampled_from(JSON_VALUES))))  # never the shared one
        if not path:
            obj = new if kind == "replace" else obj
            continue
        parent = obj
        for k in path[:-1]:
            parent = parent[k]
        key = path[-1]
        if kind == "replace":
            parent[key] = new
        elif kind == "delete":
            del parent[key]
        elif isinstance(parent, list):
            parent.insert(key, json.loads(json.dumps(parent[key])))
    text = json.dumps(obj)
    if raw_inject is not None:
        # Splice a raw (possibly invalid) token in place of the first number in the text.
        m = re.search(r"-?\d+(\.\d+)?(e[-+]?\d+)?", text)
        if m:
            text = text[:m.start()] + raw_inject + text[m.end():]
    if draw(st.integers(0, 4)) == 0:
        return draw(corrupt_text(text))
    return text.encode("utf-8", "surrogatepass")


# ----------------------------------------------------------------------------- PLY headers

PLY_TYPES = ["float", "double", "uchar", "char", "int", "uint", "short", "float32", "bogus"]


@st.composite
def corrupt_ply(draw, data: bytes) -> bytes:
    """A PLY file after 1..3 edits of its header, its body or both.

    Header: element counts, property types and names, format, extra elements; body: byte edits,
    NaN/Inf in float32 slots; both: byte edits anywhere.
    """
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header, body = data[:end].decode("ascii"), data[end:]
    anywhere = False
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["count", "count", "type", "drop_prop", "dup_prop", "rename",
                                     "format", "element", "body", "body", "nan", "anywhere"]))
        anywhere = anywhere or kind == "anywhere"
        lines = header.split("\n")
        idx = {k: [i for i, ln in enumerate(lines) if ln.startswith(k)]
               for k in ("element", "property", "format")}
        if kind == "count" and idx["element"]:
            i = draw(st.sampled_from(idx["element"]))
            w = lines[i].split()
            n = draw(st.one_of(st.sampled_from(COUNTS + [10**18, 10**19, -1]),
                               st.integers(0, 64)))
            lines[i] = f"element {w[1]} {n}"
        elif kind == "type" and idx["property"]:
            i = draw(st.sampled_from(idx["property"]))
            name = lines[i].split()[-1]
            t = draw(st.sampled_from(PLY_TYPES + ["list uchar float", "list uint double"]))
            lines[i] = f"property {t} {name}"
        elif kind == "drop_prop" and idx["property"]:
            del lines[draw(st.sampled_from(idx["property"]))]
        elif kind == "dup_prop" and idx["property"]:
            i = draw(st.sampled_from(idx["property"]))
            lines.insert(i, lines[i])
        elif kind == "rename" and idx["property"]:
            i = draw(st.sampled_from(idx["property"]))
            w = lines[i].split()
            w[-1] = draw(st.sampled_from(["f_rest_x", "f_rest_99", "x", "opacity", "red", "zz"]))
            lines[i] = " ".join(w)
        elif kind == "format" and idx["format"]:
            fmt = draw(st.sampled_from(["ascii", "binary_big_endian", "binary_little_endian",
                                        "binary_middle_endian"]))
            lines[idx["format"][0]] = f"format {fmt} 1.0"
        elif kind == "element":
            i = draw(st.sampled_from(idx["element"] + [len(lines) - 2]))
            extra = draw(st.sampled_from([
                ["element face 2", "property list uchar int vertex_indices"],
                ["element meta 1", "property uchar a"], ["element vertex 1", "property float x"],
                ["element empty 5"]]))
            lines[i:i] = extra
        elif kind == "body":
            body = draw(corrupt_bytes(body))
        elif kind == "nan" and len(body) >= 4:
            off = 4 * draw(st.integers(0, len(body) // 4 - 1))
            body = body[:off] + pack("f", draw(st.sampled_from(FLOATS))) + body[off + 4:]
        header = "\n".join(lines)
    data = header.encode("ascii") + body
    return draw(corrupt_bytes(data)) if anywhere else data
