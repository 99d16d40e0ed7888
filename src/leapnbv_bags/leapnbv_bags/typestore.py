"""The message types a bag is written and read with: ROS 2 Jazzy's, plus leapnbv_msgs' from their ``.msg`` files."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Dict, List, Mapping, Optional

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from leapnbv_bags.errors import BagError

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

__all__ = ["find_leapnbv_msg_dir", "load_leapnbv_msg_definitions", "make_typestore", "normalize_msgtype",
           "register_definitions"]


def find_leapnbv_msg_dir() -> Path:
    """Locate the directory holding leapnbv_msgs' ``*.msg`` files.

    Looks, in order, at ``$LEAPNBV_MSGS_DIR``, the source tree next to this package
    (``src/leapnbv_msgs/msg``) and ``share/leapnbv_msgs/msg`` under each ``$AMENT_PREFIX_PATH``
    entry (the colcon install space).

    Returns:
        The directory.

    Raises:
        BagError: No candidate directory holds ``.msg`` files.
    """
    candidates: List[Path] = []
    env_dir = os.environ.get("LEAPNBV_MSGS_DIR")
    if env_dir:
        candidates.append(Path(env_dir))
    candidates.append(Path(__file__).resolve().parents[2] / "leapnbv_msgs" / "msg")
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            candidates.append(Path(prefix) / "share" / "leapnbv_msgs" / "msg")
    for candidate in candidates:
        if candidate.is_dir() and any(candidate.glob("*.msg")):
            return candidate
    raise BagError("no leapnbv_msgs .msg files found in: " + ", ".join(str(c) for c in candidates))


def load_leapnbv_msg_definitions(msg_dir: Optional[Path] = None) -> Dict[str, str]:
    """Read every ``*.msg`` file of leapnbv_msgs.

    Args:
        msg_dir: Directory of the ``.msg`` files; found with :func:`find_leapnbv_msg_dir` if None.

    Returns:
        Map from type name (``leapnbv_msgs/msg/SceneGroundTruth``) to the ``.msg`` text.

    Raises:
        BagError: The directory holds no ``.msg`` file.
    """
    directory = Path(msg_dir) if msg_dir is not None else find_leapnbv_msg_dir()
    files = sorted(directory.glob("*.msg"))
    if not files:
        raise BagError(f"{directory}: no .msg files")
    return {"leapnbv_msgs/msg/" + f.stem: f.read_text(encoding="utf-8") for f in files}


def make_typestore(extra_definitions: Optional[Mapping[str, str]] = None) -> Typestore:
    """Build a ROS 2 Jazzy typestore with leapnbv_msgs (and any extra ``.msg`` types) registered.

    Args:
        extra_definitions: More type name -> ``.msg`` text pairs to register.

    Returns:
        The typestore.

    Raises:
        BagError: A definition does not parse.
    """
    typestore = get_typestore(Stores.ROS2_JAZZY)
    definitions = dict(load_leapnbv_msg_definitions())
    if extra_definitions:
        definitions.update(extra_definitions)
    register_definitions(typestore, definitions)
    return typestore


def register_definitions(typestore: Typestore, definitions: Mapping[str, str]) -> None:
    """Register ``.msg`` texts (type name -> text) that the typestore does not know yet."""
    types: Dict[str, Any] = {}
    for msgtype, text in definitions.items():
        name = normalize_msgtype(msgtype)
        if name in typestore.fielddefs:
            continue
        try:
            types.update(get_types_from_msg(text, name))
        except Exception as error:  # rosbags raises TypesysError and parser errors
            raise BagError(f"message definition of {name} does not parse: {error}") from error
    if types:
        typestore.register(types)


def normalize_msgtype(msgtype: str) -> str:
    """Turn ``pkg/Type`` into ``pkg/msg/Type`` (rosbags' and rosbag2's spelling)."""
    parts = msgtype.split("/")
    if len(parts) == 2:
        return parts[0] + "/msg/" + parts[1]
    return msgtype
