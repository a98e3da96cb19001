from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class InvalidPoses(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    INVALID_POSES_REFUSE: _ClassVar[InvalidPoses]
    INVALID_POSES_REPORT: _ClassVar[InvalidPoses]
INVALID_POSES_REFUSE: InvalidPoses
INVALID_POSES_REPORT: InvalidPoses

class Pose2D(_message.Message):
    __slots__ = ("keypoints", "confidence", "missing", "format", "intrinsics", "image_size", "person_height_m")
    KEYPOINTS_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    MISSING_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    IMAGE_SIZE_FIELD_NUMBER: _ClassVar[int]
    PERSON_HEIGHT_M_FIELD_NUMBER: _ClassVar[int]
    keypoints: _containers.RepeatedScalarFieldContainer[float]
    confidence: _containers.RepeatedScalarFieldContainer[float]
    missing: _containers.RepeatedScalarFieldContainer[bool]
    format: str
    intrinsics: CameraIntrinsics
    image_size: ImageSize
    person_height_m: float
    def __init__(self, keypoints: _Optional[_Iterable[float]] = ..., confidence: _Optional[_Iterable[float]] = ..., missing: _Optional[_Iterable[bool]] = ..., format: _Optional[str] = ..., intrinsics: _Optional[_Union[CameraIntrinsics, _Mapping]] = ..., image_size: _Optional[_Union[ImageSize, _Mapping]] = ..., person_height_m: _Optional[float] = ...) -> None: ...

class ImageSize(_message.Message):
    __slots__ = ("width", "height")
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    width: float
    height: float
    def __init__(self, width: _Optional[float] = ..., height: _Optional[float] = ...) -> None: ...

class CameraIntrinsics(_message.Message):
    __slots__ = ("fx", "fy", "cx", "cy")
    FX_FIELD_NUMBER: _ClassVar[int]
    FY_FIELD_NUMBER: _ClassVar[int]
    CX_FIELD_NUMBER: _ClassVar[int]
    CY_FIELD_NUMBER: _ClassVar[int]
    fx: float
    fy: float
    cx: float
    cy: float
    def __init__(self, fx: _Optional[float] = ..., fy: _Optional[float] = ..., cx: _Optional[float] = ..., cy: _Optional[float] = ...) -> None: ...

class LiftRequest(_message.Message):
    __slots__ = ("poses", "format", "confidence_threshold", "intrinsics", "image_size", "model", "person_height_m", "invalid_poses")
    POSES_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_THRESHOLD_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    IMAGE_SIZE_FIELD_NUMBER: _ClassVar[int]
    MODEL_FIELD_NUMBER: _ClassVar[int]
    PERSON_HEIGHT_M_FIELD_NUMBER: _ClassVar[int]
    INVALID_POSES_FIELD_NUMBER: _ClassVar[int]
    poses: _containers.RepeatedCompositeFieldContainer[Pose2D]
    format: str
    confidence_threshold: float
    intrinsics: CameraIntrinsics
    image_size: ImageSize
    model: str
    person_height_m: float
    invalid_poses: InvalidPoses
    def __init__(self, poses: _Optional[_Iterable[_Union[Pose2D, _Mapping]]] = ..., format: _Optional[str] = ..., confidence_threshold: _Optional[float] = ..., intrinsics: _Optional[_Union[CameraIntrinsics, _Mapping]] = ..., image_size: _Optional[_Union[ImageSize, _Mapping]] = ..., model: _Optional[str] = ..., person_height_m: _Optional[float] = ..., invalid_poses: _Optional[_Union[InvalidPoses, str]] = ...) -> None: ...

class PoseError(_message.Message):
    __slots__ = ("pose", "error")
    POSE_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    pose: int
    error: FrameError
    def __init__(self, pose: _Optional[int] = ..., error: _Optional[_Union[FrameError, _Mapping]] = ...) -> None: ...

class PoseResult(_message.Message):
    __slots__ = ("pose_3d", "pose_3d_camera", "camera", "scale", "rotation", "reprojection", "reprojection_error_px", "visible", "imputed", "derived", "plausibility", "warnings", "temporal", "track_id", "root_camera_m", "root_height_source")
    POSE_3D_FIELD_NUMBER: _ClassVar[int]
    POSE_3D_CAMERA_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    SCALE_FIELD_NUMBER: _ClassVar[int]
    ROTATION_FIELD_NUMBER: _ClassVar[int]
    REPROJECTION_FIELD_NUMBER: _ClassVar[int]
    REPROJECTION_ERROR_PX_FIELD_NUMBER: _ClassVar[int]
    VISIBLE_FIELD_NUMBER: _ClassVar[int]
    IMPUTED_FIELD_NUMBER: _ClassVar[int]
    DERIVED_FIELD_NUMBER: _ClassVar[int]
    PLAUSIBILITY_FIELD_NUMBER: _ClassVar[int]
    WARNINGS_FIELD_NUMBER: _ClassVar[int]
    TEMPORAL_FIELD_NUMBER: _ClassVar[int]
    TRACK_ID_FIELD_NUMBER: _ClassVar[int]
    ROOT_CAMERA_M_FIELD_NUMBER: _ClassVar[int]
    ROOT_HEIGHT_SOURCE_FIELD_NUMBER: _ClassVar[int]
    pose_3d: _containers.RepeatedScalarFieldContainer[float]
    pose_3d_camera: _containers.RepeatedScalarFieldContainer[float]
    camera: _containers.RepeatedScalarFieldContainer[float]
    scale: float
    rotation: _containers.RepeatedScalarFieldContainer[float]
    reprojection: _containers.RepeatedScalarFieldContainer[float]
    reprojection_error_px: float
    visible: _containers.RepeatedScalarFieldContainer[bool]
    imputed: _containers.RepeatedScalarFieldContainer[bool]
    derived: _containers.RepeatedScalarFieldContainer[bool]
    plausibility: float
    warnings: _containers.RepeatedScalarFieldContainer[str]
    temporal: bool
    track_id: str
    root_camera_m: _containers.RepeatedScalarFieldContainer[float]
    root_height_source: str
    def __init__(self, pose_3d: _Optional[_Iterable[float]] = ..., pose_3d_camera: _Optional[_Iterable[float]] = ..., camera: _Optional[_Iterable[float]] = ..., scale: _Optional[float] = ..., rotation: _Optional[_Iterable[float]] = ..., reprojection: _Optional[_Iterable[float]] = ..., reprojection_error_px: _Optional[float] = ..., visible: _Optional[_Iterable[bool]] = ..., imputed: _Optional[_Iterable[bool]] = ..., derived: _Optional[_Iterable[bool]] = ..., plausibility: _Optional[float] = ..., warnings: _Optional[_Iterable[str]] = ..., temporal: _Optional[bool] = ..., track_id: _Optional[str] = ..., root_camera_m: _Optional[_Iterable[float]] = ..., root_height_source: _Optional[str] = ...) -> None: ...

class LiftResponse(_message.Message):
    __slots__ = ("model_id", "joints", "poses", "errors")
    MODEL_ID_FIELD_NUMBER: _ClassVar[int]
    JOINTS_FIELD_NUMBER: _ClassVar[int]
    POSES_FIELD_NUMBER: _ClassVar[int]
    ERRORS_FIELD_NUMBER: _ClassVar[int]
    model_id: str
    joints: _containers.RepeatedScalarFieldContainer[str]
    poses: _containers.RepeatedCompositeFieldContainer[PoseResult]
    errors: _containers.RepeatedCompositeFieldContainer[PoseError]
    def __init__(self, model_id: _Optional[str] = ..., joints: _Optional[_Iterable[str]] = ..., poses: _Optional[_Iterable[_Union[PoseResult, _Mapping]]] = ..., errors: _Optional[_Iterable[_Union[PoseError, _Mapping]]] = ...) -> None: ...

class LiftFrame(_message.Message):
    __slots__ = ("frame_id", "pose", "confidence_threshold", "track_id", "fps", "people", "model")
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_THRESHOLD_FIELD_NUMBER: _ClassVar[int]
    TRACK_ID_FIELD_NUMBER: _ClassVar[int]
    FPS_FIELD_NUMBER: _ClassVar[int]
    PEOPLE_FIELD_NUMBER: _ClassVar[int]
    MODEL_FIELD_NUMBER: _ClassVar[int]
    frame_id: int
    pose: Pose2D
    confidence_threshold: float
    track_id: str
    fps: float
    people: _containers.RepeatedCompositeFieldContainer[TrackedPose]
    model: str
    def __init__(self, frame_id: _Optional[int] = ..., pose: _Optional[_Union[Pose2D, _Mapping]] = ..., confidence_threshold: _Optional[float] = ..., track_id: _Optional[str] = ..., fps: _Optional[float] = ..., people: _Optional[_Iterable[_Union[TrackedPose, _Mapping]]] = ..., model: _Optional[str] = ...) -> None: ...

class TrackedPose(_message.Message):
    __slots__ = ("track_id", "pose")
    TRACK_ID_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    track_id: str
    pose: Pose2D
    def __init__(self, track_id: _Optional[str] = ..., pose: _Optional[_Union[Pose2D, _Mapping]] = ...) -> None: ...

class PersonResult(_message.Message):
    __slots__ = ("track_id", "pose", "error")
    TRACK_ID_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    track_id: str
    pose: PoseResult
    error: FrameError
    def __init__(self, track_id: _Optional[str] = ..., pose: _Optional[_Union[PoseResult, _Mapping]] = ..., error: _Optional[_Union[FrameError, _Mapping]] = ...) -> None: ...

class FieldViolation(_message.Message):
    __slots__ = ("field", "reason", "code", "joint_name", "joint")
    FIELD_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    CODE_FIELD_NUMBER: _ClassVar[int]
    JOINT_NAME_FIELD_NUMBER: _ClassVar[int]
    JOINT_FIELD_NUMBER: _ClassVar[int]
    field: str
    reason: str
    code: str
    joint_name: str
    joint: int
    def __init__(self, field: _Optional[str] = ..., reason: _Optional[str] = ..., code: _Optional[str] = ..., joint_name: _Optional[str] = ..., joint: _Optional[int] = ...) -> None: ...

class FrameError(_message.Message):
    __slots__ = ("code", "message", "violations")
    CODE_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    VIOLATIONS_FIELD_NUMBER: _ClassVar[int]
    code: int
    message: str
    violations: _containers.RepeatedCompositeFieldContainer[FieldViolation]
    def __init__(self, code: _Optional[int] = ..., message: _Optional[str] = ..., violations: _Optional[_Iterable[_Union[FieldViolation, _Mapping]]] = ...) -> None: ...

class LiftFrameResult(_message.Message):
    __slots__ = ("frame_id", "model_id", "pose", "error", "people")
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    MODEL_ID_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    PEOPLE_FIELD_NUMBER: _ClassVar[int]
    frame_id: int
    model_id: str
    pose: PoseResult
    error: FrameError
    people: _containers.RepeatedCompositeFieldContainer[PersonResult]
    def __init__(self, frame_id: _Optional[int] = ..., model_id: _Optional[str] = ..., pose: _Optional[_Union[PoseResult, _Mapping]] = ..., error: _Optional[_Union[FrameError, _Mapping]] = ..., people: _Optional[_Iterable[_Union[PersonResult, _Mapping]]] = ...) -> None: ...
