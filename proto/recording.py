"""Recordings: JSON Lines (optionally gzip) and a compact msgpack stream.

Both hold keypoint messages in arrival order with the wire fields. A reader either
stops at the first bad record with its line (or record index) and field, or, with
``skip_bad=True``, skips it and counts it.
"""

from __future__ import annotations

import gzip
import io
import json
import os
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Iterator

import msgpack

from .keypoints import KeypointMessage, MessageError, from_dict, to_dict


class RecordingError(ValueError):
    def __init__(self, path: str | os.PathLike, line: int, error: str):
        self.path, self.line, self.error = str(path), line, error
        super().__init__(f"{path}:{line}: {error}")


@dataclass
class ReadStats:
    """What a tolerant read skipped, by reason."""

    read: int = 0
    skipped: int = 0
    reasons: Counter = field(default_factory=Counter)
    first_errors: list[str] = field(default_factory=list)

    def skip(self, err: RecordingError) -> None:
        self.skipped += 1
        # the field of a bad message, or the kind of damage ("not JSON", "unreadable tail")
        self.reasons[err.error.split(":")[0].split(" (")[0]] += 1
        if len(self.first_errors) < 10:
            self.first_errors.append(str(err))


def is_msgpack(path: str | os.PathLike) -> bool:
    name = str(path)
    return name.endswith((".msgpack", ".mpk", ".msgpack.gz", ".mpk.gz"))


def _open(path: str | os.PathLike, mode: str) -> IO:
    enc = {"encoding": "utf-8"} if "t" in mode else {}
    if str(path).endswith(".gz"):
        return gzip.open(path, mode, **enc)
    return open(path, mode, **enc)


def read_recording(
    path: str | os.PathLike, *, skip_bad: bool = False, stats: ReadStats | None = None
) -> Iterator[KeypointMessage]:
    """Yield the messages of a recording in file order.

    Raises RecordingError (path, 1-based line or record number, field and reason)
    on the first bad record unless ``skip_bad``; then bad records go to ``stats``.
    """
    stats = stats if stats is not None else ReadStats()
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"recording {path} does not exist")
    records = _msgpack_records(path) if is_msgpack(path) else _jsonl_records(path)
    for lineno, item in records:
        try:
            if isinstance(item, RecordingError):
                raise item
            try:
                msg = from_dict(item, default_version=1)
            except MessageError as e:
                raise RecordingError(path, lineno, str(e)) from None
        except RecordingError as e:
            if not skip_bad:
                raise
            stats.skip(e)
            continue
        stats.read += 1
        yield msg


def _jsonl_records(path: Path) -> Iterator[tuple[int, object]]:
    lineno = 0
    try:
        with _open(path, "rt") as f:
            for lineno, line in enumerate(f, 1):
                if not line.strip():
                    continue
                try:
                    yield lineno, json.loads(line)
                except json.JSONDecodeError as e:
                    yield lineno, RecordingError(path, lineno, f"not JSON ({e.msg})")
    except (OSError, EOFError, UnicodeDecodeError) as e:
        # A truncated gzip tail (crash while writing) ends the file, it does not poison it.
        yield lineno + 1, RecordingError(path, lineno + 1, f"unreadable tail ({type(e).__name__}: {e})")


def _msgpack_records(path: Path) -> Iterator[tuple[int, object]]:
    with _open(path, "rb") as f:
        unpacker = msgpack.Unpacker(f, raw=False, strict_map_key=True)
        n = 0
        while True:
            n += 1
            try:
                item = unpacker.unpack()
            except msgpack.OutOfData:
                return
            except Exception as e:
                yield n, RecordingError(path, n, f"not msgpack ({type(e).__name__}: {e})")
                return  # a msgpack stream cannot resynchronise after garbage
            yield n, item


class RecordingWriter:
    """Append messages to a recording; the format follows the file name.

    ``.jsonl``/``.jsonl.gz`` → JSON Lines, ``.msgpack``/``.mpk`` (optionally .gz) →
    msgpack stream. ``flush()`` pushes everything written so far to the OS.
    """

    def __init__(self, path: str | os.PathLike, *, append: bool = False):
        self.path = Path(path)
        self.count = 0
        self._msgpack = is_msgpack(self.path)
        self._gz: gzip.GzipFile | None = None
        self._raw: IO | None = None
        if str(self.path).endswith(".gz"):
            # gzip members can be flushed independently; a crash loses only the open member.
            # No name and no time in the header: the same messages give the same bytes.
            self._raw = open(self.path, "ab" if append else "wb")
            self._gz = gzip.GzipFile(filename="", mode="wb", fileobj=self._raw, compresslevel=6, mtime=0)
            self._f: IO = self._gz if self._msgpack else io.TextIOWrapper(self._gz, encoding="utf-8")
        else:
            mode = ("a" if append else "w") + ("b" if self._msgpack else "t")
            self._f = open(self.path, mode, buffering=io.DEFAULT_BUFFER_SIZE,
                           **({} if self._msgpack else {"encoding": "utf-8"}))

    def write(self, msg: KeypointMessage) -> None:
        d = to_dict(msg, packed=False)
        if self._msgpack:
            self._f.write(msgpack.packb(d, use_bin_type=True))
        else:
            self._f.write(json.dumps(d, separators=(",", ":")) + "\n")
        self.count += 1

    def flush(self) -> None:
        self._f.flush()
        if self._gz is not None:
            self._gz.flush(zlib.Z_SYNC_FLUSH)  # readable up to here after a crash
        target = self._raw if self._raw is not None else self._f
        try:
            os.fsync(target.fileno())
        except (OSError, AttributeError, io.UnsupportedOperation):
            pass

    def close(self) -> None:
        try:
            self._f.close()
        finally:
            if self._raw is not None:
                self._raw.close()

    def __enter__(self) -> "RecordingWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_recording(path: str | os.PathLike, messages) -> int:
    with RecordingWriter(path) as w:
        for m in messages:
            w.write(m)
        return w.count
