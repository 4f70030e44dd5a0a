from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class DType(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    DTYPE_UNSPECIFIED: _ClassVar[DType]
    DTYPE_FLOAT32: _ClassVar[DType]
    DTYPE_FLOAT16: _ClassVar[DType]
    DTYPE_FLOAT64: _ClassVar[DType]
    DTYPE_INT32: _ClassVar[DType]
    DTYPE_INT64: _ClassVar[DType]
    DTYPE_UINT8: _ClassVar[DType]

class SceneState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SCENE_STATE_UNSPECIFIED: _ClassVar[SceneState]
    SCENE_STATE_UNLOADED: _ClassVar[SceneState]
    SCENE_STATE_LOADING: _ClassVar[SceneState]
    SCENE_STATE_READY: _ClassVar[SceneState]
    SCENE_STATE_FAILED: _ClassVar[SceneState]

class GaussianField(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    GAUSSIAN_FIELD_UNSPECIFIED: _ClassVar[GaussianField]
    GAUSSIAN_FIELD_SIMILARITY: _ClassVar[GaussianField]
    GAUSSIAN_FIELD_MEAN: _ClassVar[GaussianField]
    GAUSSIAN_FIELD_OPACITY: _ClassVar[GaussianField]
    GAUSSIAN_FIELD_SCALE: _ClassVar[GaussianField]
    GAUSSIAN_FIELD_ROTATION: _ClassVar[GaussianField]
    GAUSSIAN_FIELD_COLOR: _ClassVar[GaussianField]
    GAUSSIAN_FIELD_INSTANCE: _ClassVar[GaussianField]

class RenderOutput(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    RENDER_OUTPUT_UNSPECIFIED: _ClassVar[RenderOutput]
    RENDER_OUTPUT_RELEVANCY: _ClassVar[RenderOutput]
    RENDER_OUTPUT_RGB: _ClassVar[RenderOutput]
    RENDER_OUTPUT_DEPTH: _ClassVar[RenderOutput]
    RENDER_OUTPUT_ALPHA: _ClassVar[RenderOutput]

class ImageEncoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    IMAGE_ENCODING_UNSPECIFIED: _ClassVar[ImageEncoding]
    IMAGE_ENCODING_FLOAT32: _ClassVar[ImageEncoding]
    IMAGE_ENCODING_PNG: _ClassVar[ImageEncoding]
DTYPE_UNSPECIFIED: DType
DTYPE_FLOAT32: DType
DTYPE_FLOAT16: DType
DTYPE_FLOAT64: DType
DTYPE_INT32: DType
DTYPE_INT64: DType
DTYPE_UINT8: DType
SCENE_STATE_UNSPECIFIED: SceneState
SCENE_STATE_UNLOADED: SceneState
SCENE_STATE_LOADING: SceneState
SCENE_STATE_READY: SceneState
SCENE_STATE_FAILED: SceneState
GAUSSIAN_FIELD_UNSPECIFIED: GaussianField
GAUSSIAN_FIELD_SIMILARITY: GaussianField
GAUSSIAN_FIELD_MEAN: GaussianField
GAUSSIAN_FIELD_OPACITY: GaussianField
GAUSSIAN_FIELD_SCALE: GaussianField
GAUSSIAN_FIELD_ROTATION: GaussianField
GAUSSIAN_FIELD_COLOR: GaussianField
GAUSSIAN_FIELD_INSTANCE: GaussianField
RENDER_OUTPUT_UNSPECIFIED: RenderOutput
RENDER_OUTPUT_RELEVANCY: RenderOutput
RENDER_OUTPUT_RGB: RenderOutput
RENDER_OUTPUT_DEPTH: RenderOutput
RENDER_OUTPUT_ALPHA: RenderOutput
IMAGE_ENCODING_UNSPECIFIED: ImageEncoding
IMAGE_ENCODING_FLOAT32: ImageEncoding
IMAGE_ENCODING_PNG: ImageEncoding

class Tensor(_message.Message):
    __slots__ = ("dtype", "shape", "data")
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    dtype: DType
    shape: _containers.RepeatedScalarFieldContainer[int]
    data: bytes
    def __init__(self, dtype: _Optional[_Union[DType, str]] = ..., shape: _Optional[_Iterable[int]] = ..., data: _Optional[bytes] = ...) -> None: ...

class Camera(_message.Message):
    __slots__ = ("viewmat", "fx", "fy", "cx", "cy", "width", "height", "near")
    VIEWMAT_FIELD_NUMBER: _ClassVar[int]
    FX_FIELD_NUMBER: _ClassVar[int]
    FY_FIELD_NUMBER: _ClassVar[int]
    CX_FIELD_NUMBER: _ClassVar[int]
    CY_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    NEAR_FIELD_NUMBER: _ClassVar[int]
    viewmat: _containers.RepeatedScalarFieldContainer[float]
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    near: float
    def __init__(self, viewmat: _Optional[_Iterable[float]] = ..., fx: _Optional[float] = ..., fy: _Optional[float] = ..., cx: _Optional[float] = ..., cy: _Optional[float] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., near: _Optional[float] = ...) -> None: ...

class SceneInfo(_message.Message):
    __slots__ = ("name", "state", "reason", "encoder_id", "embedding_dim", "num_gaussians", "num_embedded", "sh_degree", "has_field", "canonical_phrases", "label_names", "resident_bytes", "version", "bounds", "frame_id")
    NAME_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    ENCODER_ID_FIELD_NUMBER: _ClassVar[int]
    EMBEDDING_DIM_FIELD_NUMBER: _ClassVar[int]
    NUM_GAUSSIANS_FIELD_NUMBER: _ClassVar[int]
    NUM_EMBEDDED_FIELD_NUMBER: _ClassVar[int]
    SH_DEGREE_FIELD_NUMBER: _ClassVar[int]
    HAS_FIELD_FIELD_NUMBER: _ClassVar[int]
    CANONICAL_PHRASES_FIELD_NUMBER: _ClassVar[int]
    LABEL_NAMES_FIELD_NUMBER: _ClassVar[int]
    RESIDENT_BYTES_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    BOUNDS_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    name: str
    state: SceneState
    reason: str
    encoder_id: str
    embedding_dim: int
    num_gaussians: int
    num_embedded: int
    sh_degree: int
    has_field: bool
    canonical_phrases: _containers.RepeatedScalarFieldContainer[str]
    label_names: _containers.RepeatedScalarFieldContainer[str]
    resident_bytes: int
    version: str
    bounds: _containers.RepeatedScalarFieldContainer[float]
    frame_id: str
    def __init__(self, name: _Optional[str] = ..., state: _Optional[_Union[SceneState, str]] = ..., reason: _Optional[str] = ..., encoder_id: _Optional[str] = ..., embedding_dim: _Optional[int] = ..., num_gaussians: _Optional[int] = ..., num_embedded: _Optional[int] = ..., sh_degree: _Optional[int] = ..., has_field: _Optional[bool] = ..., canonical_phrases: _Optional[_Iterable[str]] = ..., label_names: _Optional[_Iterable[str]] = ..., resident_bytes: _Optional[int] = ..., version: _Optional[str] = ..., bounds: _Optional[_Iterable[float]] = ..., frame_id: _Optional[str] = ...) -> None: ...

class ListScenesRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ListScenesResponse(_message.Message):
    __slots__ = ("scenes",)
    SCENES_FIELD_NUMBER: _ClassVar[int]
    scenes: _containers.RepeatedCompositeFieldContainer[SceneInfo]
    def __init__(self, scenes: _Optional[_Iterable[_Union[SceneInfo, _Mapping]]] = ...) -> None: ...

class SceneRequest(_message.Message):
    __slots__ = ("scene",)
    SCENE_FIELD_NUMBER: _ClassVar[int]
    scene: str
    def __init__(self, scene: _Optional[str] = ...) -> None: ...

class InstanceOptions(_message.Message):
    __slots__ = ("enabled", "eps", "min_points", "max_instances")
    ENABLED_FIELD_NUMBER: _ClassVar[int]
    EPS_FIELD_NUMBER: _ClassVar[int]
    MIN_POINTS_FIELD_NUMBER: _ClassVar[int]
    MAX_INSTANCES_FIELD_NUMBER: _ClassVar[int]
    enabled: bool
    eps: float
    min_points: int
    max_instances: int
    def __init__(self, enabled: _Optional[bool] = ..., eps: _Optional[float] = ..., min_points: _Optional[int] = ..., max_instances: _Optional[int] = ...) -> None: ...

class TextQueryRequest(_message.Message):
    __slots__ = ("scene", "texts", "top_k", "threshold", "fields", "instances", "canonical_phrases", "embeddings", "encoder_id")
    SCENE_FIELD_NUMBER: _ClassVar[int]
    TEXTS_FIELD_NUMBER: _ClassVar[int]
    TOP_K_FIELD_NUMBER: _ClassVar[int]
    THRESHOLD_FIELD_NUMBER: _ClassVar[int]
    FIELDS_FIELD_NUMBER: _ClassVar[int]
    INSTANCES_FIELD_NUMBER: _ClassVar[int]
    CANONICAL_PHRASES_FIELD_NUMBER: _ClassVar[int]
    EMBEDDINGS_FIELD_NUMBER: _ClassVar[int]
    ENCODER_ID_FIELD_NUMBER: _ClassVar[int]
    scene: str
    texts: _containers.RepeatedScalarFieldContainer[str]
    top_k: int
    threshold: float
    fields: _containers.RepeatedScalarFieldContainer[GaussianField]
    instances: InstanceOptions
    canonical_phrases: _containers.RepeatedScalarFieldContainer[str]
    embeddings: Tensor
    encoder_id: str
    def __init__(self, scene: _Optional[str] = ..., texts: _Optional[_Iterable[str]] = ..., top_k: _Optional[int] = ..., threshold: _Optional[float] = ..., fields: _Optional[_Iterable[_Union[GaussianField, str]]] = ..., instances: _Optional[_Union[InstanceOptions, _Mapping]] = ..., canonical_phrases: _Optional[_Iterable[str]] = ..., embeddings: _Optional[_Union[Tensor, _Mapping]] = ..., encoder_id: _Optional[str] = ...) -> None: ...

class Box(_message.Message):
    __slots__ = ("center", "extent", "rotation")
    CENTER_FIELD_NUMBER: _ClassVar[int]
    EXTENT_FIELD_NUMBER: _ClassVar[int]
    ROTATION_FIELD_NUMBER: _ClassVar[int]
    center: _containers.RepeatedScalarFieldContainer[float]
    extent: _containers.RepeatedScalarFieldContainer[float]
    rotation: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, center: _Optional[_Iterable[float]] = ..., extent: _Optional[_Iterable[float]] = ..., rotation: _Optional[_Iterable[float]] = ...) -> None: ...

class Instance(_message.Message):
    __slots__ = ("id", "centroid", "aabb", "obb", "score", "num_members")
    ID_FIELD_NUMBER: _ClassVar[int]
    CENTROID_FIELD_NUMBER: _ClassVar[int]
    AABB_FIELD_NUMBER: _ClassVar[int]
    OBB_FIELD_NUMBER: _ClassVar[int]
    SCORE_FIELD_NUMBER: _ClassVar[int]
    NUM_MEMBERS_FIELD_NUMBER: _ClassVar[int]
    id: int
    centroid: _containers.RepeatedScalarFieldContainer[float]
    aabb: Box
    obb: Box
    score: float
    num_members: int
    def __init__(self, id: _Optional[int] = ..., centroid: _Optional[_Iterable[float]] = ..., aabb: _Optional[_Union[Box, _Mapping]] = ..., obb: _Optional[_Union[Box, _Mapping]] = ..., score: _Optional[float] = ..., num_members: _Optional[int] = ...) -> None: ...

class TextQueryChunk(_message.Message):
    __slots__ = ("text_index", "text", "total", "instances", "start", "index", "relevancy", "similarity", "mean", "opacity", "scale", "rotation", "color", "instance", "elapsed_ms", "rescored", "presence")
    TEXT_INDEX_FIELD_NUMBER: _ClassVar[int]
    TEXT_FIELD_NUMBER: _ClassVar[int]
    TOTAL_FIELD_NUMBER: _ClassVar[int]
    INSTANCES_FIELD_NUMBER: _ClassVar[int]
    START_FIELD_NUMBER: _ClassVar[int]
    INDEX_FIELD_NUMBER: _ClassVar[int]
    RELEVANCY_FIELD_NUMBER: _ClassVar[int]
    SIMILARITY_FIELD_NUMBER: _ClassVar[int]
    MEAN_FIELD_NUMBER: _ClassVar[int]
    OPACITY_FIELD_NUMBER: _ClassVar[int]
    SCALE_FIELD_NUMBER: _ClassVar[int]
    ROTATION_FIELD_NUMBER: _ClassVar[int]
    COLOR_FIELD_NUMBER: _ClassVar[int]
    INSTANCE_FIELD_NUMBER: _ClassVar[int]
    ELAPSED_MS_FIELD_NUMBER: _ClassVar[int]
    RESCORED_FIELD_NUMBER: _ClassVar[int]
    PRESENCE_FIELD_NUMBER: _ClassVar[int]
    text_index: int
    text: str
    total: int
    instances: _containers.RepeatedCompositeFieldContainer[Instance]
    start: int
    index: Tensor
    relevancy: Tensor
    similarity: Tensor
    mean: Tensor
    opacity: Tensor
    scale: Tensor
    rotation: Tensor
    color: Tensor
    instance: Tensor
    elapsed_ms: float
    rescored: int
    presence: Presence
    def __init__(self, text_index: _Optional[int] = ..., text: _Optional[str] = ..., total: _Optional[int] = ..., instances: _Optional[_Iterable[_Union[Instance, _Mapping]]] = ..., start: _Optional[int] = ..., index: _Optional[_Union[Tensor, _Mapping]] = ..., relevancy: _Optional[_Union[Tensor, _Mapping]] = ..., similarity: _Optional[_Union[Tensor, _Mapping]] = ..., mean: _Optional[_Union[Tensor, _Mapping]] = ..., opacity: _Optional[_Union[Tensor, _Mapping]] = ..., scale: _Optional[_Union[Tensor, _Mapping]] = ..., rotation: _Optional[_Union[Tensor, _Mapping]] = ..., color: _Optional[_Union[Tensor, _Mapping]] = ..., instance: _Optional[_Union[Tensor, _Mapping]] = ..., elapsed_ms: _Optional[float] = ..., rescored: _Optional[int] = ..., presence: _Optional[_Union[Presence, _Mapping]] = ...) -> None: ...

class Presence(_message.Message):
    __slots__ = ("score", "found", "margin", "rival")
    SCORE_FIELD_NUMBER: _ClassVar[int]
    FOUND_FIELD_NUMBER: _ClassVar[int]
    MARGIN_FIELD_NUMBER: _ClassVar[int]
    RIVAL_FIELD_NUMBER: _ClassVar[int]
    score: float
    found: bool
    margin: float
    rival: str
    def __init__(self, score: _Optional[float] = ..., found: _Optional[bool] = ..., margin: _Optional[float] = ..., rival: _Optional[str] = ...) -> None: ...

class RenderRequest(_message.Message):
    __slots__ = ("scene", "camera", "text", "outputs", "encoding", "canonical_phrases", "sequence")
    SCENE_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    TEXT_FIELD_NUMBER: _ClassVar[int]
    OUTPUTS_FIELD_NUMBER: _ClassVar[int]
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    CANONICAL_PHRASES_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    scene: str
    camera: Camera
    text: str
    outputs: _containers.RepeatedScalarFieldContainer[RenderOutput]
    encoding: ImageEncoding
    canonical_phrases: _containers.RepeatedScalarFieldContainer[str]
    sequence: int
    def __init__(self, scene: _Optional[str] = ..., camera: _Optional[_Union[Camera, _Mapping]] = ..., text: _Optional[str] = ..., outputs: _Optional[_Iterable[_Union[RenderOutput, str]]] = ..., encoding: _Optional[_Union[ImageEncoding, str]] = ..., canonical_phrases: _Optional[_Iterable[str]] = ..., sequence: _Optional[int] = ...) -> None: ...

class Pixel(_message.Message):
    __slots__ = ("x", "y", "value")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    VALUE_FIELD_NUMBER: _ClassVar[int]
    x: int
    y: int
    value: float
    def __init__(self, x: _Optional[int] = ..., y: _Optional[int] = ..., value: _Optional[float] = ...) -> None: ...

class RenderChunk(_message.Message):
    __slots__ = ("sequence", "width", "height", "row_start", "relevancy", "rgb", "depth", "alpha", "relevancy_png", "rgb_png", "depth_png", "alpha_png", "argmax", "elapsed_ms", "last")
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    ROW_START_FIELD_NUMBER: _ClassVar[int]
    RELEVANCY_FIELD_NUMBER: _ClassVar[int]
    RGB_FIELD_NUMBER: _ClassVar[int]
    DEPTH_FIELD_NUMBER: _ClassVar[int]
    ALPHA_FIELD_NUMBER: _ClassVar[int]
    RELEVANCY_PNG_FIELD_NUMBER: _ClassVar[int]
    RGB_PNG_FIELD_NUMBER: _ClassVar[int]
    DEPTH_PNG_FIELD_NUMBER: _ClassVar[int]
    ALPHA_PNG_FIELD_NUMBER: _ClassVar[int]
    ARGMAX_FIELD_NUMBER: _ClassVar[int]
    ELAPSED_MS_FIELD_NUMBER: _ClassVar[int]
    LAST_FIELD_NUMBER: _ClassVar[int]
    sequence: int
    width: int
    height: int
    row_start: int
    relevancy: Tensor
    rgb: Tensor
    depth: Tensor
    alpha: Tensor
    relevancy_png: bytes
    rgb_png: bytes
    depth_png: bytes
    alpha_png: bytes
    argmax: Pixel
    elapsed_ms: float
    last: bool
    def __init__(self, sequence: _Optional[int] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., row_start: _Optional[int] = ..., relevancy: _Optional[_Union[Tensor, _Mapping]] = ..., rgb: _Optional[_Union[Tensor, _Mapping]] = ..., depth: _Optional[_Union[Tensor, _Mapping]] = ..., alpha: _Optional[_Union[Tensor, _Mapping]] = ..., relevancy_png: _Optional[bytes] = ..., rgb_png: _Optional[bytes] = ..., depth_png: _Optional[bytes] = ..., alpha_png: _Optional[bytes] = ..., argmax: _Optional[_Union[Pixel, _Mapping]] = ..., elapsed_ms: _Optional[float] = ..., last: _Optional[bool] = ...) -> None: ...

class PointQueryRequest(_message.Message):
    __slots__ = ("scene", "texts", "points", "canonical_phrases")
    SCENE_FIELD_NUMBER: _ClassVar[int]
    TEXTS_FIELD_NUMBER: _ClassVar[int]
    POINTS_FIELD_NUMBER: _ClassVar[int]
    CANONICAL_PHRASES_FIELD_NUMBER: _ClassVar[int]
    scene: str
    texts: _containers.RepeatedScalarFieldContainer[str]
    points: Tensor
    canonical_phrases: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, scene: _Optional[str] = ..., texts: _Optional[_Iterable[str]] = ..., points: _Optional[_Union[Tensor, _Mapping]] = ..., canonical_phrases: _Optional[_Iterable[str]] = ...) -> None: ...

class PointQueryResponse(_message.Message):
    __slots__ = ("relevancy", "similarity", "elapsed_ms")
    RELEVANCY_FIELD_NUMBER: _ClassVar[int]
    SIMILARITY_FIELD_NUMBER: _ClassVar[int]
    ELAPSED_MS_FIELD_NUMBER: _ClassVar[int]
    relevancy: Tensor
    similarity: Tensor
    elapsed_ms: float
    def __init__(self, relevancy: _Optional[_Union[Tensor, _Mapping]] = ..., similarity: _Optional[_Union[Tensor, _Mapping]] = ..., elapsed_ms: _Optional[float] = ...) -> None: ...

class SegmentRequest(_message.Message):
    __slots__ = ("scene", "class_names", "camera", "per_gaussian")
    SCENE_FIELD_NUMBER: _ClassVar[int]
    CLASS_NAMES_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    PER_GAUSSIAN_FIELD_NUMBER: _ClassVar[int]
    scene: str
    class_names: _containers.RepeatedScalarFieldContainer[str]
    camera: Camera
    per_gaussian: bool
    def __init__(self, scene: _Optional[str] = ..., class_names: _Optional[_Iterable[str]] = ..., camera: _Optional[_Union[Camera, _Mapping]] = ..., per_gaussian: _Optional[bool] = ...) -> None: ...

class SegmentChunk(_message.Message):
    __slots__ = ("class_names", "width", "height", "pixel_labels", "gaussian_index", "gaussian_labels", "elapsed_ms", "last")
    CLASS_NAMES_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    PIXEL_LABELS_FIELD_NUMBER: _ClassVar[int]
    GAUSSIAN_INDEX_FIELD_NUMBER: _ClassVar[int]
    GAUSSIAN_LABELS_FIELD_NUMBER: _ClassVar[int]
    ELAPSED_MS_FIELD_NUMBER: _ClassVar[int]
    LAST_FIELD_NUMBER: _ClassVar[int]
    class_names: _containers.RepeatedScalarFieldContainer[str]
    width: int
    height: int
    pixel_labels: Tensor
    gaussian_index: Tensor
    gaussian_labels: Tensor
    elapsed_ms: float
    last: bool
    def __init__(self, class_names: _Optional[_Iterable[str]] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., pixel_labels: _Optional[_Union[Tensor, _Mapping]] = ..., gaussian_index: _Optional[_Union[Tensor, _Mapping]] = ..., gaussian_labels: _Optional[_Union[Tensor, _Mapping]] = ..., elapsed_ms: _Optional[float] = ..., last: _Optional[bool] = ...) -> None: ...

class GeometryRequest(_message.Message):
    __slots__ = ("scene", "max_gaussians", "min_opacity")
    SCENE_FIELD_NUMBER: _ClassVar[int]
    MAX_GAUSSIANS_FIELD_NUMBER: _ClassVar[int]
    MIN_OPACITY_FIELD_NUMBER: _ClassVar[int]
    scene: str
    max_gaussians: int
    min_opacity: float
    def __init__(self, scene: _Optional[str] = ..., max_gaussians: _Optional[int] = ..., min_opacity: _Optional[float] = ...) -> None: ...

class GeometryChunk(_message.Message):
    __slots__ = ("num_gaussians", "qualified", "total", "bounds", "start", "index", "mean", "color", "opacity", "scale", "elapsed_ms", "last")
    NUM_GAUSSIANS_FIELD_NUMBER: _ClassVar[int]
    QUALIFIED_FIELD_NUMBER: _ClassVar[int]
    TOTAL_FIELD_NUMBER: _ClassVar[int]
    BOUNDS_FIELD_NUMBER: _ClassVar[int]
    START_FIELD_NUMBER: _ClassVar[int]
    INDEX_FIELD_NUMBER: _ClassVar[int]
    MEAN_FIELD_NUMBER: _ClassVar[int]
    COLOR_FIELD_NUMBER: _ClassVar[int]
    OPACITY_FIELD_NUMBER: _ClassVar[int]
    SCALE_FIELD_NUMBER: _ClassVar[int]
    ELAPSED_MS_FIELD_NUMBER: _ClassVar[int]
    LAST_FIELD_NUMBER: _ClassVar[int]
    num_gaussians: int
    qualified: int
    total: int
    bounds: _containers.RepeatedScalarFieldContainer[float]
    start: int
    index: Tensor
    mean: Tensor
    color: Tensor
    opacity: Tensor
    scale: Tensor
    elapsed_ms: float
    last: bool
    def __init__(self, num_gaussians: _Optional[int] = ..., qualified: _Optional[int] = ..., total: _Optional[int] = ..., bounds: _Optional[_Iterable[float]] = ..., start: _Optional[int] = ..., index: _Optional[_Union[Tensor, _Mapping]] = ..., mean: _Optional[_Union[Tensor, _Mapping]] = ..., color: _Optional[_Union[Tensor, _Mapping]] = ..., opacity: _Optional[_Union[Tensor, _Mapping]] = ..., scale: _Optional[_Union[Tensor, _Mapping]] = ..., elapsed_ms: _Optional[float] = ..., last: _Optional[bool] = ...) -> None: ...
