"""Encoders and decoders for the ``image`` and ``mask`` columns.

Images are scene-linear RGB, (H, W, 3) float32 in [0, inf). Three encodings, all decoding to float32:

``png16``     16-bit RGB PNG of the fixed linear scale ``code = round(value / PNG16_LINEAR_MAX * 65535)``.
              Values above ``PNG16_LINEAR_MAX`` (4.0) are clipped, negative values clipped to 0; the step is
              6.1e-5, i.e. 0.6 % of a value of 0.01 and below 0.01 % of a value of 1.
``exr-half``  half-float OpenEXR (ZIP compression), written and read in memory. float16 keeps about 3
              significant digits over [6e-5, 65504]; larger values become inf and are refused.
``raw-f16``   a 16-byte header (magic ``RF16``, then uint32 height, width, channels, little-endian) followed
              by the little-endian float16 pixels; the Arrow IPC zstd compression of the shard compresses it.

Masks are 8-bit single-channel PNGs (0 = background, 255 = foreground); decoding gives (H, W) float32 in
[0, 1].
"""

from __future__ import annotations

import io
import struct
import sys
import warnings

import numpy as np

from relightanyone.errors import InputError

PNG16_LINEAR_MAX = 4.0
FLOAT16_MAX = 65504.0
RAW_F16_MAGIC = b"RF16"
_RAW_HEADER = struct.Struct("<4sIII")


class CodecError(InputError):
    """An image or mask cannot be encoded or decoded; the message says which and why."""


def _check_linear_image(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise CodecError(f"expected a (H, W, 3) image, got shape {image.shape}")
    image = image.astype(np.float32, copy=False)
    if not np.all(np.isfinite(image)):
        raise CodecError("image has non-finite values")
    return image


def encode_png16(image: np.ndarray, compression_level: int = 3) -> bytes:
    """(H, W, 3) linear float -> 16-bit PNG bytes on the fixed ``PNG16_LINEAR_MAX`` scale (clips)."""
    import cv2

    image = _check_linear_image(image)
    codes = np.round(np.clip(image / PNG16_LINEAR_MAX, 0.0, 1.0) * 65535.0).astype(np.uint16)
    ok, data = cv2.imencode(".png", codes[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, compression_level])
    if not ok:
        raise CodecError("OpenCV could not encode the 16-bit PNG")
    return data.tobytes()


def decode_png16(data: bytes) -> np.ndarray:
    """16-bit PNG bytes -> (H, W, 3) float32 linear."""
    import cv2

    codes = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if codes is None or codes.dtype != np.uint16 or codes.ndim != 3 or codes.shape[2] != 3:
        raise CodecError("data is not a 16-bit 3-channel PNG")
    return codes[..., ::-1].astype(np.float32) * np.float32(PNG16_LINEAR_MAX / 65535.0)


def encode_exr_half(image: np.ndarray) -> bytes:
    """(H, W, 3) linear float -> half-float OpenEXR bytes (ZIP compression, in memory)."""
    import OpenEXR

    image = _check_linear_image(image)
    if image.max(initial=0.0) > FLOAT16_MAX:
        raise CodecError(f"image values above {FLOAT16_MAX} do not fit in half floats")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    buffer = io.BytesIO()
    OpenEXR.File(header, {"RGB": np.ascontiguousarray(np.maximum(image, 0.0).astype(np.float16))}).write(
        buffer
    )
    return buffer.getvalue()


def decode_exr_half(data: bytes) -> np.ndarray:
    """OpenEXR bytes -> (H, W, 3) float32 linear (RGB channels, any pixel type)."""
    import OpenEXR

    try:
        channels = OpenEXR.File(io.BytesIO(data)).channels()
    except Exception as error:  # OpenEXR raises several types for corrupt data
        raise CodecError(f"data is not a readable OpenEXR image ({error})") from None
    if "RGB" in channels:
        pixels = channels["RGB"].pixels
    elif all(c in channels for c in "RGB"):
        pixels = np.stack([channels[c].pixels for c in "RGB"], axis=-1)
    else:
        raise CodecError(f"OpenEXR image has no RGB channels (has {sorted(channels)})")
    return np.asarray(pixels, dtype=np.float32)


def encode_raw_f16(image: np.ndarray) -> bytes:
    """(H, W, 3) linear float -> header + little-endian float16 pixels (compressed later by Arrow zstd)."""
    image = _check_linear_image(image)
    if image.max(initial=0.0) > FLOAT16_MAX:
        raise CodecError(f"image values above {FLOAT16_MAX} do not fit in half floats")
    height, width, channels = image.shape
    pixels = _to_half(np.maximum(image, 0.0))
    return _RAW_HEADER.pack(RAW_F16_MAGIC, height, width, channels) + pixels.tobytes()


# numpy converts to and from float16 one value at a time (2–6 ns each); torch's vectorized conversion
# is about 9x faster and rounds the same way (round to nearest even), so the bytes are identical.
def _to_half(values: np.ndarray) -> np.ndarray:
    import torch

    return torch.from_numpy(np.ascontiguousarray(values, dtype=np.float32)).to(torch.float16).numpy()


def _from_half(data: bytes, offset: int, shape: tuple[int, ...]) -> np.ndarray:
    """Little-endian float16 values in ``data`` from ``offset`` -> float32 array of ``shape``, converted
    straight from the bytes: torch only reads them (the copy it is handed is new), so its warning about
    a read-only buffer does not apply, and copying 6 MB to a writable buffer first would cost a third of
    the conversion."""
    import torch

    if len(data) == offset or sys.byteorder != "little":  # torch reads native order and no empty buffer
        half = np.frombuffer(data, dtype="<f2", offset=offset).astype(np.float16)
        return torch.from_numpy(half).to(torch.float32).numpy().reshape(shape)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="The given buffer is not writable", category=UserWarning)
        half = torch.frombuffer(data, dtype=torch.float16, offset=offset)
    return half.to(torch.float32).numpy().reshape(shape)


def decode_raw_f16(data: bytes) -> np.ndarray:
    """``raw-f16`` bytes -> (H, W, C) float32."""
    if len(data) < _RAW_HEADER.size:
        raise CodecError("raw-f16 data is shorter than its header")
    magic, height, width, channels = _RAW_HEADER.unpack_from(data)
    expected = _RAW_HEADER.size + height * width * channels * 2
    if magic != RAW_F16_MAGIC or len(data) != expected:
        raise CodecError(
            f"raw-f16 data is malformed (magic {magic!r}, {len(data)} bytes, expected {expected})"
        )
    return _from_half(data, _RAW_HEADER.size, (height, width, channels))


ENCODERS = {"png16": encode_png16, "exr-half": encode_exr_half, "raw-f16": encode_raw_f16}
DECODERS = {"png16": decode_png16, "exr-half": decode_exr_half, "raw-f16": decode_raw_f16}
# Chosen by bench/loader.py (numbers in docs/format.md).
DEFAULT_IMAGE_ENCODING = "raw-f16"


def encode_image(image: np.ndarray, encoding: str = DEFAULT_IMAGE_ENCODING) -> bytes:
    """(H, W, 3) linear float32 -> bytes in ``encoding``."""
    if encoding not in ENCODERS:
        raise CodecError(f"unknown image encoding {encoding!r}; use one of {sorted(ENCODERS)}")
    return ENCODERS[encoding](image)


def decode_image(data: bytes, encoding: str) -> np.ndarray:
    """Bytes in ``encoding`` -> (H, W, 3) float32 linear."""
    if encoding not in DECODERS:
        raise CodecError(f"unknown image encoding {encoding!r}; use one of {sorted(DECODERS)}")
    return DECODERS[encoding](bytes(data) if not isinstance(data, bytes) else data)


def encode_mask(mask: np.ndarray) -> bytes:
    """(H, W) mask, bool or float in [0, 1] or uint8 -> 8-bit single-channel PNG bytes."""
    import cv2

    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise CodecError(f"expected a (H, W) mask, got shape {mask.shape}")
    if mask.dtype != np.uint8:
        mask = np.round(np.clip(mask.astype(np.float32), 0.0, 1.0) * 255.0).astype(np.uint8)
    ok, data = cv2.imencode(".png", mask, [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:
        raise CodecError("OpenCV could not encode the mask PNG")
    return data.tobytes()


def decode_mask(data: bytes) -> np.ndarray:
    """8-bit PNG bytes -> (H, W) float32 in [0, 1]."""
    import cv2

    mask = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if mask is None or mask.dtype != np.uint8 or mask.ndim != 2:
        raise CodecError("data is not an 8-bit single-channel PNG mask")
    return mask.astype(np.float32) / np.float32(255.0)


def encode_valid(valid: np.ndarray) -> bytes:
    """(H, W) bool valid-pixel map -> its bits, row-major, most significant bit first (``np.packbits``):
    ``ceil(H · W / 8)`` bytes; the shard's zstd compresses the usual all-ones map to a few bytes."""
    valid = np.asarray(valid)
    if valid.ndim != 2:
        raise CodecError(f"expected a (H, W) valid-pixel map, got shape {valid.shape}")
    return np.packbits(valid.reshape(-1).astype(bool)).tobytes()


def valid_bytes(height: int, width: int) -> int:
    """Length of an encoded (height, width) valid-pixel map."""
    return -(-int(height) * int(width) // 8)


def decode_valid(data: bytes, height: int, width: int) -> np.ndarray:
    """Bits of :func:`encode_valid` -> (H, W) bool."""
    if len(data) != valid_bytes(height, width):
        raise CodecError(
            f"valid-pixel map holds {len(data)} bytes, a {width}x{height} image needs {valid_bytes(height, width)}"
        )
    bits = np.unpackbits(np.frombuffer(data, np.uint8), count=int(height) * int(width))
    return bits.reshape(int(height), int(width)).view(bool)
