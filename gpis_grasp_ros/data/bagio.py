"""rosbag2 (MCAP) reading and writing with ``rosbags`` — no ROS installation needed.

* :func:`get_typestore` — ROS 2 Jazzy types plus ``gpis_grasp_interfaces`` messages, registered
  from the interface package's own ``.msg`` text so bags and live topics agree.
* :class:`BagWriter` — writes an MCAP rosbag2 (zstd chunk compression, QoS metadata per topic).
  The output is either a single ``NAME.mcap`` file (``ros2 bag info/play NAME.mcap`` and
  ``rosbags`` read it; the rosbag2 metadata is embedded in the file) or, for a path without the
  ``.mcap`` suffix, a rosbag2 directory with ``metadata.yaml``. Everything is written to a
  temporary path next to the destination and renamed on success: an error never leaves a
  partial bag behind.
* :func:`iter_bag` / :func:`read_messages` — messages in time order with their recorded QoS.
* :func:`bag_custom_data` — the ``custom_data`` a writer stored in the rosbag2 metadata (what the
  simulator and the RGB-D importer recorded about a bag), read from ``metadata.yaml`` or from the
  MCAP file's embedded ``rosbag2`` metadata record (``rosbags``' MCAP reader does not expose it).

QoS presets follow the usual ROS 2 conventions: :data:`LATCHED_QOS` (RELIABLE,
TRANSIENT_LOCAL, KEEP_LAST 1) for ground truth published once, :data:`SENSOR_QOS`
(BEST_EFFORT, VOLATILE, KEEP_LAST 5, like ``qos_profile_sensor_data``) for camera streams.
"""

from __future__ import annotations

import os
import shutil
import struct
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from functools import lru_cache
from pathlib import Path
from typing import Any, NamedTuple

import yaml
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg
from rosbags.typesys import get_typestore as _rosbags_typestore

INTERFACE_PACKAGE = 'gpis_grasp_interfaces'
_REPO_ROOT = Path(__file__).resolve().parents[2]

_ZERO = QosTime(0, 0)  # rosbag2: "unspecified" → the middleware default (infinite)


def make_qos(reliable: bool, transient_local: bool, depth: int) -> Qos:
    """A rosbags :class:`Qos` (KEEP_LAST ``depth``, default deadline/lifespan/liveliness)."""
    return Qos(QosHistory.KEEP_LAST, int(depth),
               QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
               _ZERO, _ZERO, QosLiveliness.AUTOMATIC, _ZERO, False)


LATCHED_QOS: Qos = make_qos(reliable=True, transient_local=True, depth=1)
SENSOR_QOS: Qos = make_qos(reliable=False, transient_local=False, depth=5)


# --------------------------------------------------------------------------- typestore
def interface_msg_dir() -> Path:
    """Directory of the interface package's ``.msg`` files (source tree first, then the install)."""
    candidates = [_REPO_ROOT / INTERFACE_PACKAGE / 'msg']
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        if prefix:
            candidates.append(Path(prefix) / 'share' / INTERFACE_PACKAGE / 'msg')
    for cand in candidates:
        if cand.is_dir() and any(cand.glob('*.msg')):
            return cand
    raise FileNotFoundError(f'{INTERFACE_PACKAGE} .msg files not found in {[str(c) for c in candidates]}; '
                            'run from the repository or source install/setup.bash')


@lru_cache(maxsize=1)
def get_typestore() -> Any:
    """The shared rosbags typestore: ROS 2 Jazzy + ``gpis_grasp_interfaces/msg/*`` (cached)."""
    ts = _rosbags_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for path in sorted(interface_msg_dir().glob('*.msg')):
        types.update(get_types_from_msg(path.read_text(encoding='utf8'), f'{INTERFACE_PACKAGE}/msg/{path.stem}'))
    ts.register(types)
    return ts


# --------------------------------------------------------------------------- writing
class BagWriter:
    """Write one MCAP rosbag2, atomically. Use as a context manager::

        with BagWriter('bags/x.mcap') as bag:
            bag.add_topic('/camera/rgb/image_raw', 'sensor_msgs/msg/Image', SENSOR_QOS)
            bag.write('/camera/rgb/image_raw', t_ns, msg)

    ``path`` ending in ``.mcap`` gives a single MCAP file, anything else a rosbag2 directory.
    The destination must not exist (``overwrite=True`` replaces it only after a successful write).
    ``custom_data`` (str → str) is stored in the rosbag2 metadata. Messages are serialized with
    ``typestore`` (default :func:`get_typestore`).
    """

    def __init__(self, path: str | os.PathLike[str], *, typestore: Any = None, compress: bool = True,
                 custom_data: Mapping[str, str] | None = None, overwrite: bool = False) -> None:
        self.path = Path(path)
        self.single_file = self.path.suffix == '.mcap'
        self.typestore = typestore if typestore is not None else get_typestore()
        self.compress = compress
        self.custom_data = dict(custom_data or {})
        self.overwrite = overwrite
        self._tmpdir: Path | None = None
        self._writer: Writer | None = None
        self._connections: dict[str, Any] = {}

    def __enter__(self) -> BagWriter:
        self.open()
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def open(self) -> None:
        """Create the temporary bag next to the destination."""
        if self.path.exists() and not self.overwrite:
            raise FileExistsError(f'{self.path} exists already (pass overwrite=True to replace it)')
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmpdir = Path(tempfile.mkdtemp(prefix=f'.{self.path.name}.', suffix='.tmp', dir=self.path.parent))
        # The inner rosbag2 directory carries the final name so that the embedded metadata
        # (relative_file_paths) is correct after the rename.
        stem = self.path.stem if self.single_file else self.path.name
        writer = Writer(self._tmpdir / stem, version=9, storage_plugin=StoragePlugin.MCAP)
        if self.compress:
            writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        for key, value in sorted(self.custom_data.items()):
            writer.set_custom_data(key, value)
        writer.open()
        self._writer = writer

    def add_topic(self, topic: str, msgtype: str, qos: Qos | Iterable[Qos] = ()) -> None:
        """Declare ``topic`` of ``msgtype`` with its offered QoS profile(s)."""
        if self._writer is None:
            raise RuntimeError('BagWriter is not open')
        if topic in self._connections:
            raise ValueError(f"topic '{topic}' was added twice")
        profiles = [qos] if isinstance(qos, Qos) else list(qos)
        self._connections[topic] = self._writer.add_connection(topic, msgtype, typestore=self.typestore,
                                                               offered_qos_profiles=profiles)

    def write(self, topic: str, t_ns: int, msg: Any) -> None:
        """Serialize ``msg`` (a rosbags dataclass of the topic's type) and store it at ``t_ns`` (ns)."""
        conn = self._conn(topic)
        self._writer.write(conn, int(t_ns), bytes(self.typestore.serialize_cdr(msg, conn.msgtype)))

    def write_raw(self, topic: str, t_ns: int, raw: bytes) -> None:
        """Store already CDR-serialized ``raw`` bytes at ``t_ns`` (ns)."""
        self._writer.write(self._conn(topic), int(t_ns), raw)

    def _conn(self, topic: str) -> Any:
        if self._writer is None:
            raise RuntimeError('BagWriter is not open')
        try:
            return self._connections[topic]
        except KeyError:
            raise ValueError(f"topic '{topic}' was not added to the bag") from None

    def close(self) -> Path:
        """Finish the bag and move it into place; returns the final path."""
        if self._writer is None or self._tmpdir is None:
            raise RuntimeError('BagWriter is not open')
        try:
            self._writer.close()
            self._writer = None
            inner = self._tmpdir / (self.path.stem if self.single_file else self.path.name)
            src = inner / f'{inner.name}.mcap' if self.single_file else inner
            if self.path.exists():
                if self.path.is_dir():
                    shutil.rmtree(self.path)
                else:
                    self.path.unlink()
            os.replace(src, self.path)
        except BaseException:
            self.abort()
            raise
        shutil.rmtree(self._tmpdir, ignore_errors=True)
        self._tmpdir = None
        return self.path

    def abort(self) -> None:
        """Discard everything written so far (the destination is left untouched)."""
        if self._writer is not None:
            try:
                self._writer.abort()
            except Exception:  # noqa: BLE001 - best effort clean-up
                pass
            self._writer = None
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None


# --------------------------------------------------------------------------- reading
class BagRecord(NamedTuple):
    """One stored message: topic, type name, bag time (ns), CDR bytes and the offered QoS."""

    topic: str
    msgtype: str
    t_ns: int
    raw: bytes
    qos: tuple[Qos, ...]


def _check_bag_path(path: Path) -> None:
    if not path.exists():
        raise FileNotFoundError(f'bag {path} does not exist')


def bag_topics(path: str | os.PathLike[str]) -> dict[str, dict[str, Any]]:
    """Topic → ``{'type', 'count', 'qos'}`` of a bag (a ``.mcap`` file or rosbag2 directory)."""
    path = Path(path)
    _check_bag_path(path)
    out: dict[str, dict[str, Any]] = {}
    with AnyReader([path]) as reader:
        for conn in reader.connections:
            entry = out.setdefault(conn.topic, {'type': conn.msgtype, 'count': 0, 'qos': ()})
            entry['count'] += conn.msgcount
            entry['qos'] = tuple(getattr(conn.ext, 'offered_qos_profiles', ()) or ())
    return out


def _normalise_topics(topics: Iterable[str] | None) -> set[str] | None:
    if topics is None:
        return None
    return {t if t.startswith('/') else '/' + t for t in topics}


def _iter_raw(path: str | os.PathLike[str], topics: Iterable[str] | None) -> Iterator[tuple[Any, int, bytes, Any]]:
    """``(connection, t_ns, raw, reader)`` of the selected topics in time order."""
    path = Path(path)
    _check_bag_path(path)
    wanted = _normalise_topics(topics)
    with AnyReader([path]) as reader:
        conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
        for conn, t_ns, raw in reader.messages(connections=conns):
            yield conn, int(t_ns), raw, reader


def iter_bag(path: str | os.PathLike[str], topics: Iterable[str] | None = None) -> Iterator[BagRecord]:
    """Raw messages of a bag in time order; ``topics`` selects (with or without leading '/')."""
    for conn, t_ns, raw, _ in _iter_raw(path, topics):
        yield BagRecord(conn.topic, conn.msgtype, t_ns, bytes(raw),
                        tuple(getattr(conn.ext, 'offered_qos_profiles', ()) or ()))


def read_messages(path: str | os.PathLike[str],
                  topics: Iterable[str] | None = None) -> Iterator[tuple[str, str, int, Any]]:
    """Deserialized messages ``(topic, msgtype, t_ns, msg)`` in time order (rosbags dataclasses)."""
    for conn, t_ns, raw, reader in _iter_raw(path, topics):
        yield conn.topic, conn.msgtype, t_ns, reader.deserialize(raw, conn.msgtype)


# --------------------------------------------------------------------------- metadata
_MCAP_MAGIC = b'\x89MCAP0\r\n'
_MCAP_FOOTER, _MCAP_METADATA = 0x02, 0x0C


def _mcap_string(buf: bytes, pos: int) -> tuple[str, int]:
    (n,) = struct.unpack_from('<I', buf, pos)
    return buf[pos + 4:pos + 4 + n].decode('utf8'), pos + 4 + n


def _mcap_metadata(path: Path) -> dict[str, dict[str, str]]:
    """Name → key/value map of the top-level Metadata records of an MCAP file (chunks are skipped)."""
    out: dict[str, dict[str, str]] = {}
    with open(path, 'rb') as f:
        if f.read(len(_MCAP_MAGIC)) != _MCAP_MAGIC:
            raise ValueError(f'{path}: not an MCAP file')
        while True:
            head = f.read(9)
            if len(head) < 9:
                break
            opcode, (length,) = head[0], struct.unpack('<Q', head[1:])
            if opcode == _MCAP_FOOTER:
                break
            if opcode != _MCAP_METADATA:
                f.seek(length, os.SEEK_CUR)
                continue
            body = f.read(length)
            name, pos = _mcap_string(body, 0)
            (size,) = struct.unpack_from('<I', body, pos)
            pos, end, entries = pos + 4, pos + 4 + size, {}
            while pos < end:
                key, pos = _mcap_string(body, pos)
                entries[key], pos = _mcap_string(body, pos)
            out[name] = entries
    return out


def bag_custom_data(path: str | os.PathLike[str]) -> dict[str, str]:
    """The ``custom_data`` (str → str) of a bag's rosbag2 metadata; empty when it has none."""
    path = Path(path)
    _check_bag_path(path)
    if path.is_dir():
        text = (path / 'metadata.yaml').read_text(encoding='utf8')
    else:
        text = _mcap_metadata(path).get('rosbag2', {}).get('serialized_metadata', '')
    info = yaml.safe_load(text) if text else {}
    # metadata.yaml nests it under rosbag2_bagfile_information; the MCAP record holds that mapping itself
    info = (info or {}).get('rosbag2_bagfile_information', info or {})
    return {str(k): str(v) for k, v in (info.get('custom_data') or {}).items()}
