"""Wire schema of extrcal: keypoint message v1, recordings, Zenoh key expressions."""

from .keypoints import (
    COCO17,
    N_JOINTS,
    KeypointMessage,
    MessageError,
    Person,
    decode,
    encode,
    from_dict,
    to_dict,
)
from .recording import ReadStats, RecordingError, RecordingWriter, read_recording, write_recording

__all__ = [
    "COCO17", "N_JOINTS", "KeypointMessage", "MessageError", "Person", "decode", "encode",
    "from_dict", "to_dict", "ReadStats", "RecordingError", "RecordingWriter",
    "read_recording", "write_recording",
]
