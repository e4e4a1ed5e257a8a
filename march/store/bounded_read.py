"""Files read safely: confined names, no links, sizes bounded before reading, strict JSON.

What ``march.sim2sim`` and ``march.robot`` read of a bundle (``<stem>.deploy.json``, the ONNX
file, ``<stem>.<course>.mjb.gz``) comes through here, before the bundle's schema
(``march.sim2sim.bundle_schema``) reads a value; so do a run's ``status.json`` and
``config.yaml`` and every checkpoint (:func:`open_regular`):

- :func:`open_regular`: a path opened without following a symbolic link as its last part
  (O_NOFOLLOW: what is checked is what is read), a regular file of at most a limit;
- :func:`read_in_folder`: a plain file name inside the bundle's folder (no directory part, no
  ``..``, not absolute), opened without following a symbolic link (O_NOFOLLOW), a regular file,
  its size checked against the limit of its kind *before* it is read;
- :func:`parse_json_strict`: JSON as data only: a key given twice, ``NaN`` / ``Infinity`` (not
  JSON) and nesting deeper than :data:`MAX_JSON_DEPTH` are refused;
- :func:`gunzip_bounded`: a gzip stream inflated in pieces, refused as soon as its output passes
  the limit (a small file that inflates to gigabytes never reaches memory);
- :func:`check_yaml_plain`: YAML as march writes it (``OmegaConf.to_yaml``): no anchor, no
  alias (a "billion laughs" file of 1 KB expands to gigabytes in any loader that follows
  them), no tag, nesting and node count bounded; checked on the parser's events, which are
  as many as the text holds, before any loader builds a node;
- :func:`read_bytes`, :func:`read_json`, :func:`read_yaml_text`: a file opened as
  :func:`open_regular` does, read once, and (JSON) parsed strictly or (YAML) checked.

Every refusal is a :class:`FileRefused` (a ``ValueError``): one line. Standard library only
(the robot-side loop imports no torch).
"""

from __future__ import annotations

import json
import os
import stat
import zlib
from pathlib import Path
from typing import Any

MAX_SPEC_BYTES = 16 << 20
"""``deploy.json``: ~1 MB for the paper's courses (each cell's footholds); 16 MB is generous."""
MAX_ONNX_BYTES = 1 << 30
"""The student's ONNX graph is ~10 MB."""
MAX_SCENE_BYTES = 1 << 30
"""A course's compiled MJB, inflated: 71 MB for the smoke bundle's courses (35 MB packed)."""
MAX_INFLATION = 16
"""An MJB packs about 2:1 (measured 2.0 on both courses); a scene that inflates more than this
many times its packed size is not one march wrote, and is refused at that size."""
MAX_JSON_DEPTH = 64
"""``deploy.json`` nests 6 deep."""
MAX_YAML_BYTES = 1 << 20
"""A run's config.yaml is ~10 KB; a larger one is not a file march wrote."""
MAX_YAML_NODES = 200_000
"""A run's config.yaml has ~1,000 scalars (~3,000 parser events)."""
MAX_SUMMARY_BYTES = 16 << 20
"""``summary.json``, ``bench.json``, an audit's JSON: a few KB to a few MB."""


class FileRefused(ValueError):
    """A bundle file that is not read: one line naming it and why."""


class NotParsed(FileRefused):
    """A file that is not valid JSON / YAML text at all (cut short, not text): a reader that
    lists broken runs (the figures) may note it and go on; any other refusal (a link, a size,
    a key given twice, a YAML alias) is a file march did not write."""


def open_regular(path: Path, label: str, limit: int, wanted: str) -> Any:
    """``path`` opened for binary reading, or :class:`FileRefused` in one line naming ``label``
    (``wanted``: what to pass instead, for a missing file)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except FileNotFoundError:
        raise FileRefused(f"{label}: no such file; pass {wanted}") from None
    except OSError as err:
        if os.path.islink(path):
            raise FileRefused(
                f"{label}: is a symbolic link (to {os.readlink(path)}); march reads no run file "
                "through a link: pass the file itself"
            ) from None
        raise FileRefused(f"{label}: cannot be read ({os.strerror(err.errno)})") from None
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        raise FileRefused(f"{label}: not a regular file; pass {wanted}")
    if st.st_size > limit:
        os.close(fd)
        raise FileRefused(
            f"{label}: {st.st_size} bytes, more than the {limit} a march file of its kind can be"
        )
    return os.fdopen(fd, "rb")


def read_bytes(path: Path, label: str, limit: int, wanted: str) -> bytes:
    """The bytes of ``path`` read once through :func:`open_regular` (no link, a regular file of
    at most ``limit`` bytes; a file that grows while it is read is refused too)."""
    with open_regular(Path(path), label, limit, wanted) as f:
        size = os.fstat(f.fileno()).st_size
        data = f.read(size + 1)  # its size + 1, not limit + 1: read(n) allocates n bytes
    if len(data) > size:
        raise FileRefused(f"{label}: grew while it was read; not read")
    return data


def read_json(path: Path, label: str, limit: int = MAX_SUMMARY_BYTES, wanted: str = "") -> Any:
    """``path`` read through :func:`read_bytes` and parsed by :func:`parse_json_strict` (a key
    given twice, NaN / Infinity, nesting past :data:`MAX_JSON_DEPTH`: refused)."""
    return parse_json_strict(read_bytes(path, label, limit, wanted or "a JSON file"), label)


def read_yaml_text(
    path: Path, label: str, limit: int = MAX_YAML_BYTES, wanted: str = "a run's config.yaml"
) -> str:
    """The text of the YAML file ``path``, read through :func:`read_bytes` and checked by
    :func:`check_yaml_plain`: safe to hand to any YAML loader (``OmegaConf.create``)."""
    data = read_bytes(path, label, limit, wanted)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise NotParsed(f"{label}: not UTF-8 text ({err.reason} at byte {err.start})") from None
    check_yaml_plain(text, label)
    return text


def check_yaml_plain(text: str, label: str) -> None:
    """:class:`FileRefused` unless ``text`` is YAML as march writes it: one document, no anchor
    (``&a``), no alias (``*a``, ``<<: *a``), no explicit tag (``!!python/...``, ``!x``), at
    most :data:`MAX_JSON_DEPTH` levels and :data:`MAX_YAML_NODES` parser events. The parser's
    events are streamed: an alias is seen as one event, never expanded."""
    import yaml  # PyYAML, which OmegaConf reads with; lazily: the robot side reads no YAML

    depth = events = 0
    try:
        for event in yaml.parse(text, Loader=yaml.SafeLoader):
            events += 1
            if events > MAX_YAML_NODES:
                raise FileRefused(f"{label}: more than {MAX_YAML_NODES} YAML nodes; not read")
            if isinstance(event, yaml.AliasEvent):
                raise FileRefused(
                    f"{label}: holds a YAML alias (*{event.anchor}), which march never writes "
                    "(an alias can expand a small file to gigabytes); not read"
                )
            if getattr(event, "anchor", None) is not None:
                raise FileRefused(
                    f"{label}: holds a YAML anchor (&{event.anchor}), which march never writes; "
                    "not read"
                )
            tag = getattr(event, "tag", None)
            if tag is not None:
                raise FileRefused(f"{label}: holds a YAML tag ({tag}), which march never writes")
            if isinstance(event, yaml.CollectionStartEvent):
                depth += 1
                if depth > MAX_JSON_DEPTH:
                    raise FileRefused(f"{label}: nested deeper than {MAX_JSON_DEPTH} levels")
            elif isinstance(event, yaml.CollectionEndEvent):
                depth -= 1
            elif isinstance(event, yaml.DocumentStartEvent) and events > 2:
                raise FileRefused(f"{label}: holds more than one YAML document")
    except yaml.YAMLError as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise NotParsed(f"{label}: not readable YAML ({first})") from None


def read_in_folder(folder: Path, name: Any, what: str, limit: int) -> bytes:
    """The bytes of the file ``name`` in ``folder`` (see the module's rules) or
    :class:`FileRefused`. ``what``: how the message names the file."""
    if not isinstance(name, str) or not name or name in (".", "..") or "/" in name or "\\" in name:
        raise FileRefused(f"deploy.json: the {what} {name!r} is not a file name inside the bundle")
    path = Path(folder) / name
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | os.O_CLOEXEC)
    except FileNotFoundError:
        raise FileRefused(f"{path}: the bundle's {what} is missing") from None
    except OSError as err:  # ELOOP: a link; EACCES; ...
        why = "a symbolic link (not followed)" if path.is_symlink() else err.strerror
        raise FileRefused(f"{path}: the bundle's {what} cannot be read: {why}") from None
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise FileRefused(f"{path}: the bundle's {what} is not a regular file")
        if st.st_size > limit:
            raise FileRefused(
                f"{path}: the bundle's {what} is {st.st_size} bytes, more than the {limit} it can "
                "be; not read"
            )
        # Its size + 1, not limit + 1: read(n) allocates n bytes before it reads any.
        data = f.read(st.st_size + 1)
    if len(data) > limit or len(data) > st.st_size:  # grew while being read
        raise FileRefused(f"{path}: the bundle's {what} grew while it was read; not read")
    return data


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise FileRefused(f"the key {k!r} is given twice")
        out[k] = v
    return out


def _not_json(word: str) -> Any:
    raise NotParsed(f"{word} is not a JSON number")  # an older writer's NaN: not hostile


def _depth(node: Any) -> int:
    depth, level = 0, [node]
    while level:
        depth += 1
        if depth > MAX_JSON_DEPTH:
            return depth
        level = [
            v
            for n in level
            if isinstance(n, dict | list)
            for v in (n.values() if isinstance(n, dict) else n)
        ]
    return depth


def parse_json_strict(data: bytes, label: str) -> Any:
    """``data`` as JSON (UTF-8), data only; :class:`FileRefused` naming ``label``."""
    try:
        doc = json.loads(
            data.decode("utf-8"), object_pairs_hook=_no_duplicates, parse_constant=_not_json
        )
    except FileRefused as err:
        raise type(err)(f"{label}: not strict JSON ({err})") from None
    except (UnicodeDecodeError, ValueError, RecursionError) as err:
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise NotParsed(f"{label}: not readable JSON ({first})") from None
    if _depth(doc) > MAX_JSON_DEPTH:
        raise FileRefused(f"{label}: nested deeper than {MAX_JSON_DEPTH} levels")
    return doc


def gunzip_bounded(packed: bytes, limit: int, label: str) -> bytes:
    """The gzip stream ``packed`` inflated, at most ``limit`` bytes, else :class:`FileRefused`.
    Inflated twice: first counted with each piece dropped, so that a bomb is refused holding
    one piece whatever its ratio (the tools' refusals stay under 200 MB resident, issue 59);
    then, within the bound, kept."""
    _inflate(packed, limit, label, keep=False)
    return _inflate(packed, limit, label, keep=True)


def _inflate(packed: bytes, limit: int, label: str, keep: bool) -> bytes:
    inflater = zlib.decompressobj(wbits=16 + zlib.MAX_WBITS)
    out, size, rest = [], 0, packed
    try:
        while not inflater.eof:
            piece = inflater.decompress(rest, 1 << 20)
            rest = inflater.unconsumed_tail
            size += len(piece)
            if size > limit:
                raise FileRefused(f"{label}: inflates to more than {limit} bytes; not loaded")
            if keep:
                out.append(piece)
            if not piece and not rest:
                break
        if not inflater.eof:
            raise FileRefused(f"{label}: a truncated gzip stream")
    except zlib.error as err:
        raise FileRefused(f"{label}: not a gzip stream ({err})") from None
    if inflater.unused_data:
        raise FileRefused(f"{label}: data after its gzip stream")
    return b"".join(out)
