"""Reading rosbag2 bags (MCAP or sqlite3 storage, CDR) without a ROS install: the one bag
reader of the project, used by :class:`~splat_slam_ros.io.bagio.BagDataset` (decoded frames)
and the ROS bag player (raw CDR bytes republished as they are).

Backends: ``rosbags`` (a rosbag2 folder with ``metadata.yaml``) and ``mcap`` + ``mcap_ros2``
(a bare ``.mcap`` file, or ``backend="mcap"``). The typestore (ROS 2 Jazzy + the project's
``splat_slam_msgs`` from ``msg_defs/``) lives here too.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Dict, Iterator, List, Tuple

import yaml

from splat_slam_ros.io import mcap_recover
from splat_slam_ros.types import DatasetError

INFO_FILE = "splat_slam_info.yaml"
MSG_PACKAGE = "splat_slam_msgs"
MSG_DIR = Path(__file__).resolve().parents[2] / "msg_defs" / "msg"   # the repository's msg_defs/


def register_project_types(typestore, msg_dir=None) -> List[str]:
    """Register ``splat_slam_msgs/msg/*`` from ``msg_defs/msg/*.msg`` into a rosbags typestore.

    Returns the registered type names; an absent folder registers nothing (no error).
    """
    from rosbags.typesys import get_types_from_msg
    d = Path(msg_dir) if msg_dir is not None else MSG_DIR
    if not d.is_dir():
        return []
    types = {}
    for f in sorted(d.glob("*.msg")):
        types.update(get_types_from_msg(f.read_text(), f"{MSG_PACKAGE}/msg/{f.stem}"))
    if types:
        typestore.register(types)
    return sorted(types)


def make_typestore(project_types: bool = True):
    """ROS 2 Jazzy typestore (+ the project's own messages when msg_defs/ is present)."""
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_JAZZY)
    if project_types:
        register_project_types(ts)
    return ts


def is_bag_dir(p: Path) -> bool:
    return p.is_dir() and (p / "metadata.yaml").is_file()


class _RosbagsBackend:
    def __init__(self, path: Path):
        from rosbags.rosbag2 import Reader
        from rosbags.rosbag2.errors import ReaderError
        try:
            self.reader = Reader(path)
            self.reader.open()
        except ReaderError as e:
            raise DatasetError(f"cannot read bag {path}: {e}") from None
        self.ts = make_typestore()
        self.custom = _custom_data(path)

    def topics(self) -> Dict[str, Tuple[str, int]]:
        return {t: (i.msgtype, i.msgcount) for t, i in self.reader.topics.items()}

    def raw_messages(self, topics) -> Iterator[Tuple[str, int, bytes]]:
        conns = [c for c in self.reader.connections if c.topic in topics]
        for c, t, raw in self.reader.messages(connections=conns):
            yield c.topic, t, raw

    def messages(self, topics) -> Iterator[Tuple[str, int, Decode]]:
        """(topic, log_ns, decode()) in log-time order; decoding is deferred."""
        conns = [c for c in self.reader.connections if c.topic in topics]
        for c, t, raw in self.reader.messages(connections=conns):
            yield c.topic, t, (lambda raw=raw, c=c: self.ts.deserialize_cdr(raw, c.msgtype))

    def close(self):
        self.reader.close()


class _McapBackend:
    def __init__(self, files: List[Path]):
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory
        self.files = files
        self._make_reader = make_reader
        self._factory = DecoderFactory()
        self.custom = {}
        self._topics: Dict[str, Tuple[str, int]] = {}
        # a file whose recorder was killed (no footer / index) is read as a stream up to the damage
        self.damaged = {f: h for f in files for h in [mcap_recover.scan_mcap(f)] if h.damaged}
        for h in self.damaged.values():
            mcap_recover.warn_damaged(h)
            for t, (name, n) in h.topics.items():
                self._topics[t] = (name, self._topics.get(t, (name, 0))[1] + n)
        for f in files:
            if f in self.damaged:
                continue
            try:
                with open(f, "rb") as fh:
                    r = make_reader(fh)
                    summ = r.get_summary()
                    if summ is None:
                        raise DatasetError(f"{f}: MCAP file without a summary section")
                    stats = summ.statistics.channel_message_counts if summ.statistics else {}
                    for cid, ch in summ.channels.items():
                        name = summ.schemas[ch.schema_id].name if ch.schema_id else ""
                        old = self._topics.get(ch.topic, (name, 0))[1]
                        self._topics[ch.topic] = (name, old + stats.get(cid, 0))
            except DatasetError:
                raise
            except Exception as e:   # mcap raises several exception types
                raise DatasetError(f"cannot read MCAP file {f}: {e}") from None

    def topics(self):
        return dict(self._topics)

    def raw_messages(self, topics):
        for f in self.files:
            if f in self.damaged:
                for topic, t, _schema, _ch, data in mcap_recover.iter_messages(f, topics):
                    yield topic, t, data
                continue
            with open(f, "rb") as fh:
                for _schema, ch, m in self._make_reader(fh).iter_messages(
                        topics=list(topics), log_time_order=True):
                    yield ch.topic, m.log_time, m.data

    def messages(self, topics):
        for f in self.files:
            if f in self.damaged:
                decoders = {}
                for topic, t, schema, ch, data in mcap_recover.iter_messages(f, topics):
                    if ch.id not in decoders:
                        decoders[ch.id] = self._factory.decoder_for(ch.message_encoding, schema)
                    yield topic, t, (lambda d=decoders[ch.id], b=data: d(b))
                continue
            with open(f, "rb") as fh:
                r = self._make_reader(fh)
                decoders = {}
                for schema, ch, m in r.iter_messages(topics=list(topics), log_time_order=True):
                    if ch.id not in decoders:
                        decoders[ch.id] = self._factory.decoder_for(ch.message_encoding, schema)
                    yield ch.topic, m.log_time, (lambda d=decoders[ch.id], b=m.data: d(b))

    def close(self):
        pass


def _custom_data(bag_dir: Path) -> Dict[str, str]:
    try:
        meta = yaml.safe_load((bag_dir / "metadata.yaml").read_text())
        return dict(meta["rosbag2_bagfile_information"].get("custom_data") or {})
    except (OSError, yaml.YAMLError, KeyError, TypeError, AttributeError):
        return {}


def _storage_of(bag_dir: Path) -> str:
    meta = yaml.safe_load((bag_dir / "metadata.yaml").read_text())
    return str(meta["rosbag2_bagfile_information"].get("storage_identifier", "mcap"))


def _mcap_files_of(bag_dir: Path) -> List[Path]:
    meta = yaml.safe_load((bag_dir / "metadata.yaml").read_text())
    rel = meta["rosbag2_bagfile_information"]["relative_file_paths"]
    return [bag_dir / Path(r).name for r in rel]


Decode = Callable[[], object]


class BagFile:
    """A rosbag2 folder (or a bare ``.mcap`` file) opened for reading.

    ``topics()``: {topic: (message type, count)}; ``messages(topics)``: (topic, log_ns,
    decode) in log-time order, decoding deferred; ``raw_messages(topics)``: (topic, log_ns,
    CDR bytes). ``info``: the ``splat_slam_info.yaml`` written beside the bag by
    ``splat-slam-convert`` ({} when absent); ``custom``: the bag's ``custom_data``.
    ``backend``: "auto" (rosbags for folders, mcap for a bare .mcap file), "rosbags", "mcap".
    Every problem is a :class:`DatasetError` with a one-line message.
    """

    def __init__(self, path, backend: str = "auto"):
        p = Path(path)
        if not p.exists():
            raise DatasetError(f"bag not found: {p}")
        bag_dir = p if p.is_dir() else None
        if p.is_file():
            if p.suffix.lower() != ".mcap":
                raise DatasetError(f"{p}: a bag is a rosbag2 folder or a .mcap file")
            if is_bag_dir(p.parent) and p in _mcap_files_of(p.parent):
                bag_dir = p.parent
        if bag_dir is not None and not is_bag_dir(bag_dir):
            raise DatasetError(f"{bag_dir}: not a rosbag2 folder (no metadata.yaml)")
        self.mcap_files = _mcap_files_of(bag_dir) if p.is_dir() else [p]
        if backend == "auto":
            backend = "rosbags" if bag_dir is not None else "mcap"
            if bag_dir is not None and _storage_of(bag_dir) == "mcap" and any(
                    mcap_recover.scan_mcap(f).damaged for f in self.mcap_files if f.is_file()):
                backend = "mcap"                 # rosbags rejects a file without its footer
        if backend == "rosbags":
            if bag_dir is None:
                raise DatasetError(f"{p}: the rosbags backend needs the bag folder (metadata.yaml)")
            self._backend = _RosbagsBackend(bag_dir)
        elif backend == "mcap":
            if p.is_dir():
                storage = _storage_of(p)
                if storage != "mcap":
                    raise DatasetError(f"{p}: storage {storage!r} is not mcap "
                                       "(read it with the rosbags backend)")
            self._backend = _McapBackend(self.mcap_files)
        else:
            raise DatasetError(f"unknown bag backend {backend!r} (auto, rosbags, mcap)")
        self.path, self.bag_dir, self.backend = p, bag_dir, backend
        self.info: Dict = {}
        if bag_dir is not None and (bag_dir / INFO_FILE).is_file():
            self.info = yaml.safe_load((bag_dir / INFO_FILE).read_text()) or {}
        self.custom: Dict[str, str] = self._backend.custom

    def topics(self) -> Dict[str, Tuple[str, int]]:
        """{topic: (message type, message count)} of the whole bag."""
        return self._backend.topics()

    def messages(self, topics) -> Iterator[Tuple[str, int, Decode]]:
        """(topic, log_ns, decode()) of ``topics`` in log-time order."""
        return self._backend.messages(list(topics))

    def raw_messages(self, topics) -> Iterator[Tuple[str, int, bytes]]:
        """(topic, log_ns, serialized CDR bytes) of ``topics`` in log-time order."""
        return self._backend.raw_messages(list(topics))

    def close(self) -> None:
        self._backend.close()
