"""The verified model registry: ``twohr models list | fetch | verify``.

Resolution order for a model file: the cache (``$TWOHR_CACHE/models``, default
``~/.cache/twohr/models``), then a mirror directory (``$TWOHR_MODEL_MIRROR``, else
``../shared/models`` beside the repo or the working directory), then the official URL.
Every file is checked against its sha256 before use.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import urllib.request
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Literal

import numpy as np
import yaml
from pydantic import BaseModel, Field

from .errors import ModelError
from .files import AS_OPEN, replacing

REPO_ROOT = Path(__file__).resolve().parents[1]
log = logging.getLogger("twohr.models")


class ModelSpec(BaseModel):
    """One registry entry."""

    name: str
    file: str
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    kind: str = Field(description="r2d2, yolov8, yolov5, siamese or checkpoint")
    licence: str
    source: str
    url: str | None = None
    derived_from: str | None = None
    bundled: str | None = Field(None, description="path inside the installed package, for models we ship")
    built_from: str | None = Field(None, description="registered model this file is built from on first use, by "
                                   "its ``recipe`` (twohr.quantise)")
    calibration: str | None = Field(None, description="package path of the activation ranges a built model uses")
    recipe: Literal["int8", "coarse_heads"] = Field("int8", description="how a built model is built: int8 "
                                                     "(twohr.quantise.quantise_heads_float over ``calibration``) or "
                                                     "coarse_heads (twohr.quantise.heads_before_upsample)")
    quality: dict[str, float] = Field(default_factory=dict, description="measured feature quality on the dev frames "
                                      "(`twohr features eval`, 2HR rows at input scale 0.75): rep, prec (%, mean of "
                                      "frame distances 1, 5, 10); detector.model=auto reads it")
    inputs: dict[str, str] = Field(default_factory=dict)
    outputs: dict[str, str] = Field(default_factory=dict)


@cache
def registry() -> dict[str, ModelSpec]:
    """All registered models by name."""
    text = resources.files("twohr").joinpath("models.yaml").read_text()
    return {name: ModelSpec(name=name, **entry) for name, entry in yaml.safe_load(text).items()}


def get_spec(name: str, kind: str | None = None) -> ModelSpec:
    """The registry entry for ``name``; with ``kind``, also checks that the model is of that kind."""
    models = registry()
    if name not in models:
        raise ModelError(f"unknown model {name!r}; registered models: {', '.join(sorted(models))}")
    spec = models[name]
    if kind is not None and spec.kind != kind:
        choices = sorted(n for n, s in models.items() if s.kind == kind)
        raise ModelError(f"model {name!r} is a {spec.kind} model, not {kind}; choose one of {choices}")
    return spec


#: detector.model's short names for the registered keyframe networks
KEYFRAME_NETWORKS = {"r2d2": "r2d2_WASF_N16", "faster2d2": "faster2d2_WASF_N16",
                     "faster2d2-int8": "faster2d2_WASF_N16_int8",
                     "faster2d2-int8-coarse": "faster2d2_WASF_N16_int8_coarse", "student": "twohr_student"}
#: detector.model=auto takes a network only if its %Rep and %Prec are at most this many points below R2D2's
QUALITY_FLOOR_POINTS = 2.0
QUALITY_REFERENCE = "r2d2_WASF_N16"


def keyframe_network(name: str) -> str:
    """The registry name behind a ``detector.model`` value (a short name or a registered name)."""
    return KEYFRAME_NETWORKS.get(name, name)


def descriptor_space(model: str) -> str:
    """The network whose descriptors a ``detector.model`` value gives. A built model shares its source's (the INT8
    faster2d2 gives faster2d2's, cosine 0.997); ``auto`` shares the one space all its candidates share. A map's
    descriptors match those of its own space only."""
    if model == "auto":
        spaces = {descriptor_space(name) for name in auto_candidates()}
        return spaces.pop() if len(spaces) == 1 else model
    name = keyframe_network(model)
    spec = registry().get(name)
    return name if spec is None or spec.built_from is None else descriptor_space(spec.built_from)


def auto_candidates() -> list[str]:
    """The networks ``auto`` may choose, best measured quality first: r2d2-kind models whose measured quality
    (registry ``quality``) is within :data:`QUALITY_FLOOR_POINTS` of R2D2's in both repeatability and matching
    precision. R2D2 itself, the reference, is left out while another meets the floor: it does about 3x faster2d2's
    work on any CPU."""
    models = registry()
    reference = models[QUALITY_REFERENCE].quality
    meets = [spec.name for spec in models.values() if spec.kind == "r2d2" and spec.quality
             and all(spec.quality[k] >= reference[k] - QUALITY_FLOOR_POINTS for k in ("rep", "prec"))]
    meets.sort(key=lambda name: -(models[name].quality["rep"] + models[name].quality["prec"]))
    return [name for name in meets if name != QUALITY_REFERENCE] or meets


def cache_dir() -> Path:
    return Path(os.environ.get("TWOHR_CACHE", Path.home() / ".cache" / "twohr")) / "models"


def mirror_dirs() -> list[Path]:
    """Mirror directories to copy models from, in order of preference."""
    if os.environ.get("TWOHR_MODEL_MIRROR"):
        return [Path(os.environ["TWOHR_MODEL_MIRROR"])]
    candidates = [REPO_ROOT.parent / "shared" / "models", Path.cwd().parent / "shared" / "models"]
    seen: list[Path] = []
    for c in candidates:
        if c.is_dir() and c.resolve() not in [s.resolve() for s in seen]:
            seen.append(c)
    return seen


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _how_to_get(spec: ModelSpec) -> str:
    where = f"download {spec.url}" if spec.url else f"it has no public download ({spec.source})"
    return (
        f"put {spec.file} (sha256 {spec.sha256}) in $TWOHR_MODEL_MIRROR and run `twohr models fetch {spec.name}`; "
        f"or {where}"
    )


def package_file(where: str) -> Path:
    """The file ``package:relative/path`` names inside an installed package."""
    package, _, rel = where.partition(":")
    return Path(str(resources.files(package).joinpath(rel)))


def bundled_path(spec: ModelSpec) -> Path | None:
    """The file a model ships as inside an installed package, or None for a model fetched into the cache."""
    return None if spec.bundled is None else package_file(spec.bundled)


def local_file(name: str) -> Path:
    """Where model ``name`` is on this machine without fetching it: shipped in a package (else in the cache), else
    in a mirror directory; the first when it is in none of them (it may not exist: :func:`verify_file` says so)."""
    spec = get_spec(name)
    first = bundled_path(spec) or cache_dir() / spec.file
    if first.is_file():
        return first
    return next((mirror / spec.file for mirror in mirror_dirs() if (mirror / spec.file).is_file()), first)


def _build(spec: ModelSpec, target: Path) -> Path:
    """Build ``spec`` from the model it is ``built_from`` by its ``recipe`` (INT8 with float heads over the shipped
    activation ranges, or heads before the upsample: the same bytes on every machine), verify it and move it into
    place."""
    from .quantise import heads_before_upsample, quantise_heads_float

    if spec.recipe == "int8" and spec.calibration is None:
        raise ModelError(f"model {spec.name} is built from {spec.built_from} but names no calibration ranges")
    source = fetch(spec.built_from)
    log.info("building %s from %s (%s)", spec.name, spec.built_from, spec.recipe)
    try:
        # a temporary name of its own: replicas that start together on one cache each build their own copy
        with replacing(target, AS_OPEN, suffix=".part.onnx") as building:
            built = Path(building.name)  # the recipes write by name
            if spec.recipe == "coarse_heads":
                heads_before_upsample(source, built)
            else:
                quantise_heads_float(source, built, package_file(spec.calibration))
            verify_file(spec, built)
    except ImportError as exc:
        raise ModelError(f"model {spec.name} cannot be built here: {exc}") from None
    return target


def verify_file(spec: ModelSpec, path: Path) -> None:
    """Raise :class:`ModelError` unless ``path`` holds exactly the registered bytes."""
    if not path.is_file():
        raise ModelError(f"model {spec.name} is missing: {path}. {_how_to_get(spec)}")
    actual = sha256_of(path)
    if actual != spec.sha256:
        raise ModelError(
            f"model {spec.name} at {path} fails its checksum: sha256 {actual}, expected {spec.sha256}. "
            f"Delete it and {_how_to_get(spec)}"
        )


def fetch(name: str, force: bool = False) -> Path:
    """Make the verified model file available locally and return its path."""
    spec = get_spec(name)
    bundled = bundled_path(spec)
    if bundled is not None:
        verify_file(spec, bundled)
        return bundled
    target = cache_dir() / spec.file
    if target.is_file() and not force:
        verify_file(spec, target)
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    if spec.built_from:
        return _build(spec, target)
    for mirror in mirror_dirs():
        source = mirror / spec.file
        if source.is_file():
            verify_file(spec, source)
            _atomic_copy(source, target)
            return target
    if spec.url:
        with replacing(target, AS_OPEN, suffix=".part") as downloading:
            try:
                with urllib.request.urlopen(spec.url, timeout=60) as response:
                    shutil.copyfileobj(response, downloading)
                downloading.flush()
            except OSError as exc:
                raise ModelError(
                    f"model {spec.name}: download from {spec.url} failed ({exc}). {_how_to_get(spec)}"
                ) from None
            verify_file(spec, Path(downloading.name))
        return target
    searched = ", ".join(str(m) for m in mirror_dirs()) or "no mirror directory"
    raise ModelError(f"model {spec.name} not found (searched {searched}). {_how_to_get(spec)}")


def _atomic_copy(source: Path, target: Path) -> None:
    with replacing(target, AS_OPEN, suffix=".part") as copying, open(source, "rb") as original:
        shutil.copyfileobj(original, copying)


@cache
def model_path(name: str, kind: str | None = None) -> Path:
    """Path of a verified model file, fetching it on first use. This is what the cores call."""
    get_spec(name, kind)
    return fetch(name)


def session_options(threads: int, varying_shapes: bool = False):
    """onnxruntime options every twohr network uses: ``threads`` intra-op threads, sequential, fully optimised.
    ``varying_shapes``: the inputs change shape from call to call (the matcher's candidate lists), so no memory
    pattern is planned per shape (onnxruntime keeps one for every shape it saw)."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.enable_mem_pattern = not varying_shapes
    return options


#: onnxruntime's execution providers for each backend that runs on it, preferred first.
ORT_PROVIDERS = {
    "onnxruntime": ["CPUExecutionProvider"],
    "cuda": ["CUDAExecutionProvider", "CPUExecutionProvider"],
    "tensorrt": ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"],
}
#: OpenVINO's device for each backend that runs on it.
OPENVINO_DEVICES = {"openvino": "CPU", "openvino-gpu": "GPU"}
#: Inference backends for the dense networks. ``auto`` = the first this machine has, in this order (GPUs first):
#: ``tensorrt`` and ``cuda`` (onnxruntime's NVIDIA execution providers, from the onnxruntime-gpu package),
#: ``openvino-gpu`` (an Intel GPU), ``openvino`` (CPU), ``onnxruntime`` (CPU).
BACKENDS = ("auto", "tensorrt", "cuda", "openvino-gpu", "openvino", "onnxruntime")
WHAT_IT_NEEDS = {
    "tensorrt": "onnxruntime's TensorrtExecutionProvider (the onnxruntime-gpu package with TensorRT, an NVIDIA GPU)",
    "cuda": "onnxruntime's CUDAExecutionProvider (the onnxruntime-gpu package, an NVIDIA GPU with CUDA)",
    "openvino-gpu": "an OpenVINO GPU device (an Intel GPU and its compute runtime)",
    "openvino": "the openvino package",
    "onnxruntime": "the onnxruntime package",
}


def ort_session(model: str | bytes, threads: int, backend: str = "onnxruntime", precision: str = "auto",
                varying_shapes: bool = False):
    """An onnxruntime session for a model file path or serialised model bytes, on ``backend``'s execution
    providers (:data:`ORT_PROVIDERS`; TensorRT in fp16 unless ``precision`` is ``f32``); raises
    :class:`ModelError` when a GPU backend fell back to the CPU."""
    import onnxruntime as ort

    providers: list = list(ORT_PROVIDERS[backend])
    if backend == "tensorrt":  # engines are built once per model and shape, then read from the cache
        engines = cache_dir().parent / "tensorrt"
        engines.mkdir(parents=True, exist_ok=True)
        providers[0] = ("TensorrtExecutionProvider", {"trt_engine_cache_enable": True,
                                                      "trt_engine_cache_path": str(engines),
                                                      "trt_fp16_enable": precision != "f32"})
    session = ort.InferenceSession(model, session_options(threads, varying_shapes), providers=providers)
    if session.get_providers()[0] != ORT_PROVIDERS[backend][0]:
        raise ModelError(f"backend {backend}: onnxruntime fell back to {session.get_providers()[0]}; it needs "
                         f"{WHAT_IT_NEEDS[backend]}")
    return session


def cpu_session(model: str | bytes, threads: int, varying_shapes: bool = False):
    """An onnxruntime CPU session for a model file path or serialised model bytes (see :func:`session_options`)."""
    return ort_session(model, threads, "onnxruntime", varying_shapes=varying_shapes)


@cache
def available_backends() -> tuple[str, ...]:
    """The inference backends this machine can run, in ``auto``'s order of preference (GPUs first)."""
    found = []
    try:
        import onnxruntime as ort

        providers = set(ort.get_available_providers())
    except ImportError:
        providers = set()
    # onnxruntime lists the providers it was built with (onnxruntime-gpu lists CUDA on a machine without a GPU):
    # a GPU backend counts only when a tiny model really runs on it
    found += [b for b in ("tensorrt", "cuda") if ORT_PROVIDERS[b][0] in providers and _runs_on(ORT_PROVIDERS[b][0])]
    try:
        import openvino as ov

        devices = ov.Core().available_devices
        found += ["openvino-gpu"] if any(d.startswith("GPU") for d in devices) else []
        found.append("openvino")
    except Exception:  # noqa: BLE001 - not installed, or its runtime cannot start here: not a backend here
        pass
    if "CPUExecutionProvider" in providers:
        found.append("onnxruntime")
    return tuple(found)


def _runs_on(provider: str) -> bool:
    """Whether onnxruntime runs a one-node model on ``provider`` without falling back to the CPU."""
    import onnxruntime as ort
    from onnx import TensorProto, helper

    value = helper.make_tensor_value_info
    graph = helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "probe",
                              [value("x", TensorProto.FLOAT, [1])], [value("y", TensorProto.FLOAT, [1])])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], ir_version=8)
    try:
        session = ort.InferenceSession(model.SerializeToString(), providers=[provider, "CPUExecutionProvider"])
    except Exception:  # noqa: BLE001 - a provider that cannot start is simply not there
        return False
    return session.get_providers()[0] == provider


def resolve_backend(backend: str) -> str:
    """``auto`` -> the first of :func:`available_backends`; a named backend is checked, and one this machine does
    not have is a :class:`ModelError` that says what it needs."""
    if backend not in BACKENDS:
        raise ModelError(f"unknown inference backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    available = available_backends()
    if backend == "auto":
        if not available:
            raise ModelError("no inference backend: install onnxruntime or openvino")
        return available[0]
    if backend not in available:
        raise ModelError(f"inference backend {backend} is not available here: it needs {WHAT_IT_NEEDS[backend]} "
                         f"(available: {', '.join(available) or 'none'})")
    return backend


def cpu_has_bf16() -> bool:
    """True when OpenVINO reports native bf16 on this CPU (AMX or AVX-512 BF16)."""
    try:
        import openvino as ov
    except ImportError:
        return False
    return "BF16" in ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")


class Network:
    """One compiled network, called with a dict of float32 inputs; returns its outputs by name.

    ``backend`` is one of :data:`BACKENDS` (see :func:`resolve_backend`). For OpenVINO on the CPU,
    ``precision`` is the inference precision: ``bf16`` uses AMX where the CPU has it (about 3.5x
    faster than fp32 for faster2d2 here), ``f32`` is exact, ``auto`` = bf16 where native; on a GPU
    (``openvino-gpu``) ``auto`` and ``bf16`` run f16. The model is compiled once per input shape, because static
    shapes run faster. Not thread-safe: give each thread its own, or lock.
    """

    def __init__(self, model: str | bytes, threads: int, backend: str = "auto", precision: str = "auto") -> None:
        self.backend = resolve_backend(backend)
        self.threads = threads
        if self.backend in ORT_PROVIDERS:
            self._session = ort_session(model, threads, self.backend, precision)
            self.input_names = [i.name for i in self._session.get_inputs()]
            self.output_names = [o.name for o in self._session.get_outputs()]
            return
        import openvino as ov

        self.device = OPENVINO_DEVICES[self.backend]
        if precision not in ("auto", "bf16", "f32"):
            raise ModelError(f"unknown OpenVINO precision {precision!r}; choose auto, bf16 or f32")
        if self.device == "GPU":
            precision = "f32" if precision == "f32" else "f16"
        elif precision == "auto":
            precision = "bf16" if cpu_has_bf16() else "f32"
        self.precision = precision
        self._core = ov.Core()
        self._model = self._core.read_model(model)
        self.input_names = [i.get_any_name() for i in self._model.inputs]
        self.output_names = [o.get_any_name() for o in self._model.outputs]
        self._compiled: dict[tuple, object] = {}

    def _request(self, inputs: dict[str, np.ndarray]):
        key = tuple(inputs[name].shape for name in self.input_names)
        if key not in self._compiled:
            model = self._model.clone()
            model.reshape({name: list(inputs[name].shape) for name in self.input_names})
            options = {"INFERENCE_PRECISION_HINT": self.precision, "PERFORMANCE_HINT": "LATENCY", "NUM_STREAMS": 1}
            if self.device == "CPU":
                options["INFERENCE_NUM_THREADS"] = self.threads
            compiled = self._core.compile_model(model, self.device, options)
            self._compiled[key] = compiled.create_infer_request()
        return self._compiled[key]

    def __call__(self, inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        if self.backend in ORT_PROVIDERS:
            return dict(zip(self.output_names, self._session.run(self.output_names, inputs), strict=True))
        request = self._request(inputs)
        request.infer(inputs)
        return {name: request.get_tensor(name).data for name in self.output_names}
