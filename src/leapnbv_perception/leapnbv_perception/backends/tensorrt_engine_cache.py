"""TensorRT engine cache: which engine file an ONNX model has, and loading it or building it.

Engine cache: `<cache_dir>/<onnx stem>.<precision>.<key[:20]>.engine`, where key =
sha256(sha256(ONNX bytes) | TensorRT version | GPU name | precision [| precision plan
digest, FP16 only] [| each external-data file's digest]). The default cache_dir is
`$LEAPNBV_ENGINE_CACHE`, else `~/.cache/leapnbv/tensorrt`. A cached engine that fails to
deserialize (TensorRT upgrade, truncated file) is rebuilt and overwritten. Beside each engine,
`<engine>.layers.json` records the layers the precision plan kept in FP32, so a cache hit logs
the same list. Everything here is plain Python; the TensorRT calls go through `TensorRTAdapter`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from typing import Any, List, Optional, Sequence, Tuple

from leapnbv_common.atomic_files import write_bytes_atomically
from leapnbv_perception.backends.base import BackendError, normalize_precision, require_model_file
from leapnbv_perception.backends.precision_plan import PrecisionPlan
from leapnbv_perception.backends.tensorrt_adapter import TensorRTAdapter

# The TensorRT backend's one logger: its messages are configured and filtered under one name.
LOGGER = logging.getLogger("leapnbv_perception.backends.tensorrt_backend")

ENGINE_CACHE_ENV = "LEAPNBV_ENGINE_CACHE"


def external_data_digests(onnx_path: str) -> List[str]:
    """sha256 of each file the ONNX graph keeps tensors in (external data: a graph over 2 GiB keeps
    its weights in ``<model>.onnx.data``), in the order the graph names them; [] when it has none.

    The graph's own bytes do not change when only those files do, so the engine cache key needs them.
    """
    names = [os.path.basename(onnx_path) + ".data"] if os.path.isfile(onnx_path + ".data") else []
    try:
        import onnx

        proto = onnx.load(onnx_path, load_external_data=False)
    except Exception:  # noqa: BLE001 - no onnx, or a graph it cannot read (the parser reports that):
        pass  # the project's export convention, <model>.onnx.data beside it
    else:
        names = []
        for tensor in proto.graph.initializer:
            if tensor.data_location == onnx.TensorProto.EXTERNAL:
                location = next(entry.value for entry in tensor.external_data if entry.key == "location")
                if location not in names:
                    names.append(location)
    digests = []
    for name in names:
        path = os.path.join(os.path.dirname(os.path.abspath(onnx_path)), name)
        require_model_file(path)
        digest = hashlib.sha256()
        with open(path, "rb") as stream:
            for block in iter(lambda: stream.read(1 << 22), b""):
                digest.update(block)
        digests.append(name + ":" + digest.hexdigest())
    return digests


def engine_cache_key(
    onnx_bytes: bytes, trt_version: str, gpu_name: str, precision: str, plan_digest: str = "",
    external_digests: Sequence[str] = (),
) -> str:
    """Key of a built engine: it is valid only for this ONNX, TensorRT, GPU, precision and plan.

    Args:
        onnx_bytes: the ONNX file's content.
        trt_version: tensorrt.__version__.
        gpu_name: CUDA device name, e.g. "Xavier".
        precision: "fp32" or "fp16".
        plan_digest: `PrecisionPlan.digest` of the FP16 precision plan the engine is built
            with; "" for none (the key is then the same as without a plan).
        external_digests: `external_data_digests` of the model (its weights stored outside the
            graph); empty for none (the key is then the same as before).

    Returns:
        64 hex characters.
    """
    onnx_digest = hashlib.sha256(onnx_bytes).hexdigest()
    parts = [onnx_digest, str(trt_version), str(gpu_name).strip(), normalize_precision(precision)]
    if plan_digest:
        parts.append("plan:" + plan_digest)
    parts.extend("data:" + digest for digest in external_digests)
    return hashlib.sha256("|".join(parts).encode("utf-8")).hexdigest()


def default_engine_cache_dir() -> str:
    """$LEAPNBV_ENGINE_CACHE, else ~/.cache/leapnbv/tensorrt."""
    configured = os.environ.get(ENGINE_CACHE_ENV, "").strip()
    if configured:
        return configured
    return os.path.join(os.path.expanduser("~"), ".cache", "leapnbv", "tensorrt")


def engine_cache_path(cache_dir: Optional[str], onnx_path: str, precision: str, key: str) -> str:
    """File the engine for `key` is cached in.

    Args:
        cache_dir: folder; None for `default_engine_cache_dir()`.
        onnx_path: the ONNX file (its stem names the engine for humans).
        precision: "fp32" or "fp16".
        key: `engine_cache_key(...)`.

    Returns:
        `<cache_dir>/<onnx stem>.<precision>.<key[:20]>.engine`.
    """
    folder = cache_dir if cache_dir else default_engine_cache_dir()
    stem = os.path.splitext(os.path.basename(onnx_path))[0]
    return os.path.join(folder, "%s.%s.%s.engine" % (stem, normalize_precision(precision), key[:20]))



def _plan_record_path(engine_path: str) -> str:
    return engine_path + ".layers.json"


def _log_kept_layers(engine_path: str, onnx_path: str, plan: PrecisionPlan, kept: List[str],
                     skipped: List[str], cached: bool) -> None:
    LOGGER.info(
        "TensorRT fp16 engine '%s' (%s '%s'): precision plan '%s' keeps %d layer%s in FP32: %s%s",
        engine_path, "cached, built from" if cached else "built from", onnx_path, plan.path, len(kept),
        "" if len(kept) == 1 else "s", ", ".join(kept) if kept else "(none)",
        "; skipped (outputs not floating point): %s" % ", ".join(skipped) if skipped else "",
    )


def load_or_build_engine(
    adapter: TensorRTAdapter,
    onnx_path: str,
    precision: str,
    gpu_name: str,
    cache_dir: Optional[str] = None,
    plan: Optional[PrecisionPlan] = None,
) -> Tuple[Any, str, bool, Optional[List[str]]]:
    """Deserialize the cached engine for this ONNX/TensorRT/GPU/precision/plan, or build it.

    Args:
        adapter: the TensorRT adapter.
        onnx_path: the ONNX file.
        precision: "fp32" or "fp16".
        gpu_name: device name (part of the key).
        cache_dir: engine cache folder (None: default).
        plan: FP16 precision plan; ignored (and logged so) for an fp32 engine.

    Returns:
        (engine, cache file path, True when the engine was built now, the layers the plan kept
        in FP32: None without a plan, or for a cached engine whose record file is missing).

    Raises:
        ModelFileNotFoundError: when onnx_path does not exist.
        BackendError: when building fails or the fresh engine does not deserialize.
    """
    require_model_file(onnx_path)
    with open(onnx_path, "rb") as stream:
        onnx_bytes = stream.read()
    if plan is not None and precision != "fp16":
        LOGGER.info("precision plan '%s' not used: the %s engine of '%s' runs every layer in FP32",
                    plan.path, precision, onnx_path)
        plan = None
    if plan is not None and plan.model_sha256 and plan.model_sha256 != hashlib.sha256(onnx_bytes).hexdigest():
        LOGGER.warning("precision plan '%s' was made for another ONNX (model_sha256 %s...), not '%s'",
                       plan.path, plan.model_sha256[:12], onnx_path)
    key = engine_cache_key(onnx_bytes, adapter.version, gpu_name, precision, plan.digest if plan else "",
                           external_data_digests(onnx_path))
    path = engine_cache_path(cache_dir, onnx_path, precision, key)
    if os.path.isfile(path):
        with open(path, "rb") as stream:
            engine = adapter.deserialize(stream.read())
        if engine is not None:
            kept = None
            if plan is not None:
                kept, skipped = _read_plan_record(path)
                if kept is None:
                    LOGGER.info("cached TensorRT engine '%s' was built with precision plan '%s' (its list of FP32 "
                                "layers is missing)", path, plan.path)
                else:
                    _log_kept_layers(path, onnx_path, plan, kept, skipped, cached=True)
            return engine, path, False, kept
        LOGGER.warning("cached TensorRT engine '%s' is unusable; rebuilding from '%s'", path, onnx_path)
    LOGGER.info("building TensorRT %s engine from '%s' (this takes minutes on a Jetson)", precision, onnx_path)
    serialized, kept, skipped = adapter.build_serialized(onnx_bytes, precision, onnx_path, plan)
    write_bytes_atomically(path, serialized)
    if plan is not None:
        record = {"precision_plan": plan.path, "plan_digest": plan.digest, "kept_fp32": kept, "skipped": skipped}
        write_bytes_atomically(_plan_record_path(path), (json.dumps(record, indent=1) + "\n").encode("utf-8"))
        _log_kept_layers(path, onnx_path, plan, kept, skipped, cached=False)
    engine = adapter.deserialize(serialized)
    if engine is None:
        raise BackendError("TensorRT could not deserialize the engine it just built from '%s'" % onnx_path)
    return engine, path, True, (kept if plan is not None else None)


def _read_plan_record(engine_path: str) -> Tuple[Optional[List[str]], List[str]]:
    try:
        with open(_plan_record_path(engine_path), encoding="utf-8") as stream:
            record = json.load(stream)
        return [str(name) for name in record["kept_fp32"]], [str(name) for name in record.get("skipped", [])]
    except (OSError, ValueError, KeyError, TypeError):
        return None, []
