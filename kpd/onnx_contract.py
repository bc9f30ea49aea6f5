"""The contract between the exporter (``kpd.export``, torch) and the runtime (``kpd.runtime``, onnxruntime).

Both sides import these names, so a bundle written by one is read by the other without guessing. Nothing here
imports torch or onnxruntime.

A bundle (directory ``name.kpd/`` or a zip of the same files) holds:

================== ==========================================================================================
``manifest.json``  format name and version, shapes (K, C, F, M), category, point count, normalisation, cage
                   template, W_C, the PCA prior (or null), the template point cloud's description, training
                   record, sha256 of every other file, and a checksum of the manifest itself
``keypoints.onnx`` ``points`` (B, N, 3) float32 -> ``keypoints`` (B, K, 3) float32, clamped to [-1, 1]
``influence.onnx`` ``points`` (B, N, 3) float32 -> ``influence`` (B, K, C) float32, the instance offset W_I
``template.npy``   (optional) (P, 3) float32 surface points of a representative training shape, model frame
================== ==========================================================================================

Points are in the model's [-1, 1] frame (``kpd.geometry.Normalizer``, docs/method.md §7). ``B`` and ``N`` are dynamic
axes named :data:`BATCH_AXIS` and :data:`POINTS_AXIS`.
"""

from __future__ import annotations

from typing import NamedTuple

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "MANIFEST_FILE",
    "TEMPLATE_FILE",
    "INPUT_NAME",
    "BATCH_AXIS",
    "POINTS_AXIS",
    "OPSET",
    "NORMALIZATION",
    "GraphSpec",
    "KEYPOINTS_GRAPH",
    "INFLUENCE_GRAPH",
    "GRAPHS",
    "META_FORMAT",
    "META_FORMAT_VERSION",
    "META_GRAPH",
    "META_KEYPOINTS",
    "META_CAGE_VERTICES",
    "META_CATEGORY",
    "DOMAINS",
    "graph_refusal",
]

FORMAT_NAME = "kpd-bundle"
FORMAT_VERSION = 1

MANIFEST_FILE = "manifest.json"
TEMPLATE_FILE = "template.npy"

INPUT_NAME = "points"
BATCH_AXIS = "batch"
POINTS_AXIS = "points"
OPSET = 20

# How shapes are mapped into the model frame; the runtime refuses a bundle that says anything else.
NORMALIZATION = "bbox-center-max-abs"


class GraphSpec(NamedTuple):
    """One ONNX graph of a bundle.

    key : name of the graph in the manifest and in the ``kpd.graph`` metadata entry.
    file : file name inside the bundle.
    output : name of the single output.
    output_axes : symbolic output shape; "K" and "C" are fixed per model, ``BATCH_AXIS`` is dynamic.
    """

    key: str
    file: str
    output: str
    output_axes: tuple[str, ...]


KEYPOINTS_GRAPH = GraphSpec("keypoints", "keypoints.onnx", "keypoints", (BATCH_AXIS, "K", "3"))
INFLUENCE_GRAPH = GraphSpec("influence", "influence.onnx", "influence", (BATCH_AXIS, "K", "C"))
GRAPHS = (KEYPOINTS_GRAPH, INFLUENCE_GRAPH)

# Keys of the ONNX models' metadata_props (values are strings).
META_FORMAT = "kpd.format"
META_FORMAT_VERSION = "kpd.format_version"
META_GRAPH = "kpd.graph"
META_KEYPOINTS = "kpd.keypoints"
META_CAGE_VERTICES = "kpd.cage_vertices"
META_CATEGORY = "kpd.category"

# The operator sets kpd's exporter writes graphs in (torch.onnx with opset OPSET): the default ONNX domain only. A
# bundle's graph that imports or uses another domain (com.microsoft, ai.onnx.ml, a custom one) or defines functions
# of its own is refused by the runtime.
DOMAINS = ("", "ai.onnx")

_MAX_DEPTH = 16  # subgraphs (If, Loop, Scan bodies) nested deeper than this are refused; the exporter writes none


def graph_refusal(data: bytes) -> str | None:
    """Why a serialised ONNX model is not a self-contained graph of kpd's operator sets, or None when it is.

    Refused: a tensor (an initializer, a sparse initializer, a Constant's or any attribute's tensor, in the graph or
    any subgraph) whose data lies outside the model (``data_location`` EXTERNAL or ``external_data`` entries, which
    onnxruntime would read from the current folder); an operator set import or a node of a domain other than
    :data:`DOMAINS`; model-local functions; training information; bytes that are not a protobuf message.

    The model is walked in its protobuf wire format (field numbers of onnx.proto), so the runtime needs neither the
    ``onnx`` package nor a copy of its schema; tensors' data are skipped, not read.
    """
    try:
        return _model_refusal(memoryview(data))
    except _Malformed as exc:
        return f"not an ONNX model ({exc})"


class _Malformed(Exception):
    pass


def _fields(buf: memoryview):
    """(field number, wire type, value) of each field of one protobuf message: an int for varints and fixed
    widths, a memoryview for length-delimited fields."""
    i, n = 0, len(buf)

    def varint() -> int:
        nonlocal i
        shift = result = 0
        while True:
            if i >= n or shift > 63:
                raise _Malformed("a varint runs past its message")
            b = buf[i]
            i += 1
            result |= (b & 0x7F) << shift
            if b < 0x80:
                return result
            shift += 7

    while i < n:
        key = varint()
        number, wire = key >> 3, key & 7
        if wire == 0:
            yield number, wire, varint()
        elif wire == 1 or wire == 5:
            width = 8 if wire == 1 else 4
            if i + width > n:
                raise _Malformed("a fixed-width field runs past its message")
            yield number, wire, int.from_bytes(buf[i:i + width], "little")
            i += width
        elif wire == 2:
            length = varint()
            if i + length > n:
                raise _Malformed("a field runs past its message")
            yield number, wire, buf[i:i + length]
            i += length
        else:
            raise _Malformed(f"wire type {wire}")


def _text(value) -> str:
    return bytes(value).decode("utf-8", "replace") if isinstance(value, memoryview) else ""


def _model_refusal(buf: memoryview) -> str | None:
    graph = None
    for number, wire, value in _fields(buf):
        if number == 8 and wire == 2:  # opset_import
            domain = next((_text(v) for f, w, v in _fields(value) if f == 1 and w == 2), "")
            if domain not in DOMAINS:
                return f"it imports the operator set {domain!r}; kpd's graphs use the default ONNX domain only"
        elif number == 25:
            return "it defines functions of its own; kpd's graphs have none"
        elif number == 20:
            return "it holds training information; a bundle's graphs are for inference"
        elif number == 7 and wire == 2:
            graph = value
    if graph is None:
        return "it holds no graph"
    return _graph_refusal(graph, 0)


def _graph_refusal(buf: memoryview, depth: int) -> str | None:
    if depth > _MAX_DEPTH:
        return f"subgraphs nested more than {_MAX_DEPTH} deep"
    for number, wire, value in _fields(buf):
        if wire != 2:
            continue
        if number == 1:  # node
            refusal = _node_refusal(value, depth)
        elif number == 5:  # initializer
            refusal = _tensor_refusal(value)
        elif number == 15:  # sparse_initializer
            refusal = _sparse_refusal(value)
        else:
            refusal = None
        if refusal:
            return refusal
    return None


def _node_refusal(buf: memoryview, depth: int) -> str | None:
    op, domain, attributes = "", "", []
    for number, wire, value in _fields(buf):
        if number == 4 and wire == 2:
            op = _text(value)
        elif number == 7 and wire == 2:
            domain = _text(value)
        elif number == 5 and wire == 2:
            attributes.append(value)
    if domain not in DOMAINS:
        return f"node {op!r} is of the operator set {domain!r}; kpd's graphs use the default ONNX domain only"
    for attribute in attributes:
        for number, wire, value in _fields(attribute):
            if wire != 2:
                continue
            if number in (5, 10):  # t, tensors
                refusal = _tensor_refusal(value)
            elif number in (6, 11):  # g, graphs
                refusal = _graph_refusal(value, depth + 1)
            elif number in (22, 23):  # sparse_tensor(s)
                refusal = _sparse_refusal(value)
            else:
                refusal = None
            if refusal:
                return refusal
    return None


def _sparse_refusal(buf: memoryview) -> str | None:
    """A SparseTensorProto's refusal: its values (field 1) and indices (field 2) are tensors of their own."""
    return next((r for f, w, v in _fields(buf) if f in (1, 2) and w == 2 for r in [_tensor_refusal(v)] if r), None)


def _tensor_refusal(buf: memoryview) -> str | None:
    name = ""
    external = False
    for number, wire, value in _fields(buf):
        if number == 8 and wire == 2:
            name = _text(value)
        elif (number == 14 and wire == 0 and value != 0) or (number == 13 and wire == 2):
            external = True  # data_location EXTERNAL, or external_data entries
    if external:
        return f"tensor {name!r} keeps its data outside the model (external data); a bundle holds its own data"
    return None
