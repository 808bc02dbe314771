"""Damaged MCAP files: read every complete message up to the damage, report, repair.

A recorder killed mid-run leaves an MCAP without its summary, index and footer ("File end
magic is invalid"); its data section is still a valid prefix. Such files are read as a
stream (``mcap.stream_reader``) up to the first incomplete or unreadable record; every
complete message before it is recovered (messages inside a truncated compressed chunk are
lost with that chunk). :func:`recover_bag` writes a repaired, indexed copy.
"""
from __future__ import annotations

import functools
import io
import struct
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Tuple

import lz4.frame
import zstandard
from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader


@dataclass
class McapHealth:
    """What :func:`scan_mcap` found in one MCAP file."""
    path: Path
    indexed: bool                       # readable summary + footer (an intact file)
    messages: int = 0                   # complete messages (all of them when indexed)
    topics: Dict[str, Tuple[str, int]] = field(default_factory=dict)  # topic -> (type, count)
    error: str = ""                     # why the summary / the stream stopped
    bytes_ok: int = 0                   # bytes of the file read without damage
    size: int = 0

    @property
    def damaged(self) -> bool:
        return not self.indexed

    def describe(self) -> str:
        if self.indexed:
            return f"{self.path.name}: intact ({self.messages} messages, indexed)"
        return (f"{self.path.name}: damaged, no summary/index ({self.error}); read as a stream: "
                f"{self.messages} complete messages recovered")


def _summary(path: Path):
    """The file's summary, or (None, why) when it has none / cannot be read."""
    try:
        with open(path, "rb") as fh:
            s = make_reader(fh).get_summary()
    except Exception as e:          # mcap raises several exception types for damaged files
        return None, f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
    if s is None or s.statistics is None:
        return None, "no summary section"
    return s, ""


MAGIC = b"\x89MCAP0\r\n"
OP_CHUNK, OP_FOOTER = 0x06, 0x02


def _parse(buf: bytes) -> Iterator[object]:
    """Complete records in ``buf`` (a chunk is broken up); stops at the first partial one."""
    it = StreamReader(io.BytesIO(buf), skip_magic=True).records
    while True:
        try:
            yield next(it)
        except (StopIteration, EndOfFile):
            return


def _partial_chunk(body: bytes) -> Iterator[object]:
    """The complete records at the start of a truncated chunk record (MCAP chunk layout)."""
    if len(body) < 32:
        return
    n = struct.unpack_from("<I", body, 28)[0]
    comp = body[32:32 + n].decode(errors="replace")
    data = body[32 + n + 8:]
    if comp == "zstd":
        data = zstandard.ZstdDecompressor().decompressobj().decompress(data)
    elif comp == "lz4":
        data = lz4.frame.LZ4FrameDecompressor().decompress(data)
    elif comp:
        return
    yield from _parse(data)


def _records(fh, size: int, health: Optional[McapHealth]) -> Iterator[object]:
    def stop(why: str, pos: int):
        if health is not None:
            health.error = health.error or why
            health.bytes_ok = pos
    if fh.read(8) != MAGIC:
        stop("not an MCAP file (bad start magic)", 0)
        return
    while True:
        pos = fh.tell()
        hdr = fh.read(9)
        if len(hdr) < 9:
            stop(f"file ends at byte {pos} without a footer", pos)
            return
        op, length = struct.unpack("<BQ", hdr)
        body = fh.read(min(length, max(0, size - pos - 9)))
        if len(body) < length:
            if op == OP_CHUNK:
                yield from _partial_chunk(body)
            stop(f"record at byte {pos} truncated ({len(body)} of {length} bytes)", pos)
            return
        recs = list(_parse(hdr + body))
        if op != OP_CHUNK and not recs and length:
            stop(f"unreadable record at byte {pos}", pos)
            return
        yield from recs
        if health is not None:
            health.bytes_ok = fh.tell()
        if op == OP_FOOTER:
            return


def stream_records(path: Path, health: Optional[McapHealth] = None
                   ) -> Iterator[Tuple[Schema, Channel, Message]]:
    """(schema, channel, message) of every complete message in file order, up to the damage.

    Fills ``health`` (messages, topics, error, bytes_ok) as it goes. Complete messages at the
    start of a truncated chunk are recovered too (uncompressed, zstd or lz4 chunks).
    """
    schemas: Dict[int, Schema] = {}
    channels: Dict[int, Channel] = {}
    path = Path(path)
    with open(path, "rb") as fh:
        for rec in _records(fh, path.stat().st_size, health):
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
            elif isinstance(rec, Message) and rec.channel_id in channels:
                ch = channels[rec.channel_id]
                sc = schemas.get(ch.schema_id)
                if health is not None:
                    health.messages += 1
                    name = sc.name if sc is not None else ""
                    health.topics[ch.topic] = (name, health.topics.get(ch.topic, (name, 0))[1] + 1)
                yield sc, ch, rec


def scan_mcap(path) -> McapHealth:
    """Check one MCAP file: intact (indexed) or damaged (streamed up to the damage).

    Cached per (path, size, mtime): a damaged file is streamed once however often it is opened.
    """
    path = Path(path).resolve()
    st = path.stat()
    return _scan(path, st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=64)
def _scan(path: Path, size: int, _mtime_ns: int) -> McapHealth:
    s, why = _summary(path)
    if s is not None:
        counts = s.statistics.channel_message_counts
        topics: Dict[str, Tuple[str, int]] = {}
        for cid, ch in s.channels.items():
            name = s.schemas[ch.schema_id].name if ch.schema_id in s.schemas else ""
            topics[ch.topic] = (name, topics.get(ch.topic, (name, 0))[1] + counts.get(cid, 0))
        return McapHealth(path, True, s.statistics.message_count, topics, "", size, size)
    h = McapHealth(path, False, size=size)
    for _ in stream_records(path, h):
        pass
    return h


def iter_messages(path, topics) -> Iterator[Tuple[str, int, Schema, Channel, bytes]]:
    """(topic, log_ns, schema, channel, data) of a damaged file's complete messages (file order)."""
    want = set(topics)
    for sc, ch, m in stream_records(Path(path)):
        if ch.topic in want:
            yield ch.topic, m.log_time, sc, ch, m.data


def damaged_files(files, types: Dict[str, str], counts: Dict[str, int]) -> set:
    """The damaged MCAP files among ``files`` (each warned about); adds the topics' types
    and recovered message counts of those files to ``types`` / ``counts``."""
    bad = set()
    for f in files:
        h = scan_mcap(f) if Path(f).is_file() else None
        if h is None or not h.damaged:
            continue
        bad.add(f)
        warn_damaged(h)
        for t, (name, n) in h.topics.items():
            types[t] = name
            counts[t] = counts.get(t, 0) + n
    return bad


def warn_damaged(h: McapHealth, out=None) -> None:
    """One warning line naming how many messages were recovered."""
    print(f"warning: {h.describe()}", file=out or sys.stderr, flush=True)


def recover_mcap(src, dst) -> McapHealth:
    """Copy every complete message of ``src`` into a new, indexed MCAP ``dst``."""
    from mcap.writer import Writer
    src, dst = Path(src), Path(dst)
    h = McapHealth(src, _summary(src)[0] is not None, size=src.stat().st_size)
    with open(dst, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="splat_slam_ros recover")
        sid: Dict[int, int] = {}
        cid: Dict[int, int] = {}
        for sc, ch, m in stream_records(src, h):
            if sc is not None and sc.id not in sid:
                sid[sc.id] = w.register_schema(sc.name, sc.encoding, sc.data)
            if ch.id not in cid:
                cid[ch.id] = w.register_channel(ch.topic, ch.message_encoding,
                                                sid.get(ch.schema_id, 0), dict(ch.metadata))
            w.add_message(cid[ch.id], m.log_time, m.data, m.publish_time, m.sequence)
        w.finish()
    return h


def recover_bag(src, out) -> List[McapHealth]:
    """Repair a rosbag2 folder or a bare .mcap file into ``out`` (must not exist).

    A folder keeps its layout: every MCAP is rewritten with an index, ``metadata.yaml`` gets
    the recovered message counts, other files (``splat_slam_info.yaml``) are copied.
    """
    import shutil

    import yaml
    src, out = Path(src), Path(out)
    if out.exists():
        raise FileExistsError(f"{out} exists (choose a new --out)")
    if src.is_file():
        out.parent.mkdir(parents=True, exist_ok=True)
        return [recover_mcap(src, out if out.suffix == ".mcap" else out.with_suffix(".mcap"))]
    meta_f = src / "metadata.yaml"
    meta = yaml.safe_load(meta_f.read_text())
    info = meta["rosbag2_bagfile_information"]
    out.mkdir(parents=True)
    healths = []
    for rel in info["relative_file_paths"]:
        healths.append(recover_mcap(src / Path(rel).name, out / Path(rel).name))
    for f in src.iterdir():
        if f.is_file() and f.suffix != ".mcap" and f.name != "metadata.yaml":
            shutil.copy2(f, out / f.name)
    total: Dict[str, int] = {}
    for h in healths:
        for t, (_, n) in h.topics.items():
            total[t] = total.get(t, 0) + n
    for tm in info.get("topics_with_message_count") or []:
        tm["message_count"] = total.get(tm["topic_metadata"]["name"], 0)
    info["message_count"] = sum(total.values())
    for fi in info.get("files") or []:
        fi["message_count"] = next((h.messages for h in healths
                                    if h.path.name == Path(fi["path"]).name), 0)
    (out / "metadata.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    return healths
