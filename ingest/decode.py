"""Decoding native images into scene-linear float RGB, and the colour calibration that follows.

Every :class:`~relightanyone.ingest.records.ImageRef` codec becomes ``(H, W, 3)`` float32 linear RGB:

``exr-linear``            OpenEXR (half or float), already scene-linear
``avif-srgb`` ``png-srgb`` ``jpg-srgb`` ``mp4-frame``   display codes, decoded with the sRGB transfer function
``avif-gamma22``          display codes, decoded with a pure 2.2 gamma (FaceOLAT's AVIF export)
``avif-linear`` ``png-linear``   codes holding linear values scaled to [0, 1]
``dng-raw``               rawpy: AHD demosaic in the camera's own RGB (``ColorSpace.raw``), unit white
                          balance, no auto brightness, gamma 1, 16 bit, then ``/ 65535``, so a pixel is
                          ``(raw - black) / (white - black)``. Colour comes from the chart-fitted matrix, not
                          from the camera's white balance.

8- and 16-bit PNG/JPEG go through OpenCV (``IMREAD_UNCHANGED`` keeps 16 bit), AVIF through Pillow, videos
through PyAV. A :class:`TaskDecoder` serves one ingest task: it decodes each needed video once (all the
frame indices the task asks for, in one pass), keeps zip archives open and hashes every source file
once. Anything that cannot be read raises :class:`DecodeError` naming the file and the problem; the
runner quarantines that view and carries on.
"""

from __future__ import annotations

import functools
import io
import posixpath
import zipfile
import zlib
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from relightanyone.align.colour import apply_ccm, gamma_to_linear, linear_to_srgb, srgb_to_linear
from relightanyone.errors import InputError
from relightanyone.hashing import sha256_bytes, sha256_file
from relightanyone.ingest.records import ColourCalibration, ImageRef

DISPLAY_CODECS = {"avif-srgb": "srgb", "png-srgb": "srgb", "jpg-srgb": "srgb", "mp4-frame": "srgb"}
GAMMA22_CODECS = ("avif-gamma22",)
LINEAR_CODE_CODECS = ("avif-linear", "png-linear")


class DecodeError(InputError):
    """A native image cannot be read; the message names the file (and member or frame) and why."""


# Threads of the video decoder (FFmpeg through PyAV); 0 keeps FFmpeg's default (one per CPU).
_video_threads = 0


def header_size(path: str | Path, codec: str) -> tuple[int, int] | None:
    """(width, height) of an image file from its header (no pixel decoding; EXR through OpenEXR, the other
    still formats through Pillow); None when it cannot be read (the runner reports it when it decodes)."""
    try:
        if codec == "exr-linear":
            import OpenEXR

            window = OpenEXR.InputFile(str(path)).header()["dataWindow"]
            return window.max.x - window.min.x + 1, window.max.y - window.min.y + 1
        from PIL import Image

        with Image.open(path) as image:
            return image.size
    except Exception:  # OpenEXR and Pillow raise assorted types on damaged files; the runner reports them
        return None


def set_decoder_threads(avif: int, video: int) -> None:
    """Threads of the AVIF decoder (libavif through Pillow) and of the video decoder (FFmpeg through PyAV)
    in this process; 0 restores a library's default, one thread per CPU.

    Ingest tasks use one AVIF thread and their share of the CPUs for video
    (:func:`~relightanyone.ingest.subject_task.configure_task_threads`): libavif's threads cost more than
    they save on one still image (1.1 ms with one thread, 1.5 ms with two per 167×256 image; no gain at
    667×1024), and starting a thread per CPU in every worker oversubscribes the machine as soon as two
    workers run. FFmpeg's frame threads do pay off on long, large videos. LibRaw's OpenMP demosaic and
    OpenEXR keep their own defaults.
    """
    global _video_threads
    if avif < 0 or video < 0:
        raise ValueError(f"decoder threads must be >= 0, got avif={avif}, video={video}")
    from PIL import AvifImagePlugin

    AvifImagePlugin.DEFAULT_MAX_THREADS = avif  # read by Pillow when it opens an AVIF file
    _video_threads = video


def safe_member_name(member: str) -> str:
    """Refuse zip member names that are absolute or climb out of the archive (``../x``)."""
    normal = posixpath.normpath(member.replace("\\", "/"))
    if member.startswith(("/", "\\")) or normal == ".." or normal.startswith("../") or ":" in member:
        raise DecodeError(f"zip member name {member!r} points outside the archive; refusing to read it")
    return member


def _codes_to_unit(codes: np.ndarray, where: str) -> np.ndarray:
    """Integer image codes ``(H, W[, C])`` -> float32 in [0, 1] by the dtype's full range."""
    if codes.dtype == np.uint8:
        return codes.astype(np.float32) / np.float32(255.0)
    if codes.dtype == np.uint16:
        return codes.astype(np.float32) / np.float32(65535.0)
    raise DecodeError(f"{where}: unsupported sample type {codes.dtype} (expected 8 or 16 bit)")


def _as_rgb(image: np.ndarray, where: str) -> np.ndarray:
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] < 3:
        raise DecodeError(f"{where}: expected an RGB image, got shape {image.shape}")
    return np.ascontiguousarray(image[:, :, :3])


def _decode_opencv(data: bytes, where: str) -> np.ndarray:
    """PNG / JPEG bytes -> RGB integer codes ``(H, W, 3)`` (8 or 16 bit kept)."""
    import cv2

    codes = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if codes is None:
        raise DecodeError(f"{where}: not a readable PNG/JPEG image (corrupt or truncated)")
    if codes.ndim == 3:
        codes = cv2.cvtColor(codes, cv2.COLOR_BGRA2RGB if codes.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    return _as_rgb(codes, where)


def _decode_pillow(data: bytes, where: str) -> np.ndarray:
    """AVIF (or any Pillow format) bytes -> RGB uint8 codes ``(H, W, 3)``."""
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as image:
            image.load()
            return np.asarray(image.convert("RGB"))
    except Exception as error:  # Pillow raises OSError, SyntaxError, ValueError for corrupt data
        raise DecodeError(f"{where}: not a readable AVIF image ({error})") from None


def _decode_exr(data: bytes, where: str) -> np.ndarray:
    import OpenEXR

    try:
        channels = OpenEXR.File(io.BytesIO(data)).channels()
    except Exception as error:  # OpenEXR raises several types for corrupt data
        raise DecodeError(f"{where}: not a readable OpenEXR image ({error})") from None
    if "RGB" in channels:
        pixels = np.asarray(channels["RGB"].pixels)
    elif "RGBA" in channels:
        pixels = np.asarray(channels["RGBA"].pixels)[:, :, :3]
    elif all(c in channels for c in "RGB"):
        pixels = np.stack([np.asarray(channels[c].pixels) for c in "RGB"], axis=-1)
    else:
        raise DecodeError(f"{where}: OpenEXR image has no R, G, B channels (has {sorted(channels)})")
    return pixels.astype(np.float32)


def _decode_dng(data: bytes, where: str) -> np.ndarray:
    import rawpy

    try:
        with rawpy.imread(io.BytesIO(data)) as raw:
            rgb = raw.postprocess(
                gamma=(1, 1),
                no_auto_bright=True,
                output_bps=16,
                output_color=rawpy.ColorSpace.raw,
                use_camera_wb=False,
                user_wb=[1.0, 1.0, 1.0, 1.0],
                user_flip=0,
            )
    except Exception as error:  # rawpy raises LibRawError subclasses and IOError
        raise DecodeError(f"{where}: not a readable RAW/DNG file ({error})") from None
    return rgb.astype(np.float32) / np.float32(65535.0)


@functools.lru_cache(maxsize=8)
def _code_table(codec: str, levels: int) -> np.ndarray:
    """``(levels,)`` float32 linear value of every integer code of ``codec`` (one transfer-function
    evaluation per process instead of one per pixel)."""

    unit = np.arange(levels, dtype=np.float64) / (levels - 1)
    if codec in DISPLAY_CODECS:
        return np.asarray(srgb_to_linear(unit), dtype=np.float32)
    if codec in GAMMA22_CODECS:
        return np.asarray(gamma_to_linear(unit), dtype=np.float32)
    return unit.astype(np.float32)


def codes_to_linear(codes: np.ndarray, codec: str, where: str) -> np.ndarray:
    """Decoded integer codes ``(H, W, 3)`` of ``codec`` -> scene-linear float32 ``(H, W, 3)``."""
    if codec not in DISPLAY_CODECS and codec not in GAMMA22_CODECS and codec not in LINEAR_CODE_CODECS:
        raise DecodeError(f"{where}: codec {codec!r} does not hold integer display codes")
    if codes.dtype not in (np.uint8, np.uint16):
        raise DecodeError(f"{where}: unsupported sample type {codes.dtype} (expected 8 or 16 bit)")
    if codes.dtype == np.uint8 and (codes.ndim == 2 or (codes.ndim == 3 and codes.shape[2] <= 4)):
        import cv2

        # OpenCV's table lookup is ~8x faster than NumPy indexing on 8-bit images (same values).
        return cv2.LUT(np.ascontiguousarray(codes), _code_table(codec, 256))
    return np.take(_code_table(codec, 65536 if codes.dtype == np.uint16 else 256), codes)


def decode_bytes(data: bytes, codec: str, where: str) -> np.ndarray:
    """Bytes of one still image in ``codec`` -> ``(H, W, 3)`` float32 scene-linear RGB."""
    if not data:
        raise DecodeError(f"{where}: file is empty")
    if codec == "exr-linear":
        image = _decode_exr(data, where)
    elif codec == "dng-raw":
        image = _decode_dng(data, where)
    elif codec.startswith("avif-"):
        image = codes_to_linear(_decode_pillow(data, where), codec, where)
    elif codec in ("png-srgb", "jpg-srgb", "png-linear"):
        image = codes_to_linear(_decode_opencv(data, where), codec, where)
    else:
        raise DecodeError(f"{where}: codec {codec!r} is not a still-image codec")
    image = _as_rgb(image, where)
    if not np.all(np.isfinite(image)):
        raise DecodeError(f"{where}: image holds NaN or infinite values")
    return image


def decode_alpha_bytes(data: bytes, where: str) -> np.ndarray:
    """An alpha / foreground map (PNG, JPEG or AVIF, any channel count) -> ``(H, W)`` float32 in [0, 1]."""
    import cv2

    codes = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if codes is None:
        codes = _decode_pillow(data, where)
    if codes.ndim == 3:
        # A 4-channel map carries alpha last; an RGB map is grey.
        codes = codes[:, :, 3] if codes.shape[2] == 4 else codes[:, :, 0]
    return _codes_to_unit(codes, where)


def decode_video_frames(path: Path, frame_indices: Iterable[int]) -> dict[int, np.ndarray]:
    """Decode the given frame indices of a video in one sequential pass.

    Returns ``{index: (H, W, 3) uint8 RGB}``; raises :class:`DecodeError` when the file is unreadable or
    shorter than the largest index asked for.
    """
    import av

    wanted = sorted({int(i) for i in frame_indices})
    if not wanted:
        return {}
    if wanted[0] < 0:
        raise DecodeError(f"{path}: negative frame index {wanted[0]}")
    frames: dict[int, np.ndarray] = {}
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            stream.codec_context.thread_count = _video_threads
            for index, frame in enumerate(container.decode(stream)):
                if index in wanted:
                    frames[index] = frame.to_ndarray(format="rgb24")
                if index >= wanted[-1]:
                    break
    except (av.error.FFmpegError, IndexError, OSError) as error:
        raise DecodeError(f"{path}: not a readable video ({error})") from None
    missing = [i for i in wanted if i not in frames]
    if missing:
        raise DecodeError(f"{path}: video has no frame {missing[0]} (it ends after {len(frames)} frames)")
    return frames


class TaskDecoder:
    """Decodes the images of one ingest task, reusing open archives, decoded videos and file hashes.

    ``source_root`` resolves relative ``ImageRef.path`` values. Call :meth:`prefetch_videos` with the
    task's refs first so each video is decoded once; :meth:`decode` then serves frames from memory.
    """

    def __init__(self, source_root: Path | str):
        self.source_root = Path(source_root)
        self._zips: dict[str, zipfile.ZipFile] = {}
        self._videos: dict[tuple[str, int], np.ndarray] = {}
        self._video_errors: dict[str, str] = {}
        self._hashes: dict[str, str] = {}

    def resolve(self, path: str) -> Path:
        p = Path(path)
        return p if p.is_absolute() else self.source_root / p

    def _zip(self, path: Path) -> zipfile.ZipFile:
        key = str(path)
        if key not in self._zips:
            try:
                self._zips[key] = zipfile.ZipFile(path)
            except (zipfile.BadZipFile, OSError, EOFError) as error:
                raise DecodeError(f"{path}: not a readable zip archive ({error}); is it truncated?") from None
        return self._zips[key]

    def read_bytes(self, ref: ImageRef) -> bytes:
        """The native bytes of ``ref`` (a file, or a member of a zip archive)."""
        path = self.resolve(ref.path)
        if ref.member is None:
            try:
                return path.read_bytes()
            except OSError as error:
                raise DecodeError(f"{path}: cannot read ({error.strerror or error})") from None
        member = safe_member_name(ref.member)
        archive = self._zip(path)
        try:
            return archive.read(member)
        except KeyError:
            raise DecodeError(f"{path}: zip has no member {member!r} (dropped frame?)") from None
        except (zipfile.BadZipFile, OSError, EOFError, zlib.error) as error:
            raise DecodeError(f"{path}::{member}: corrupt zip member ({error})") from None

    def prefetch_videos(self, refs: Iterable[ImageRef]) -> None:
        """Decode, per video file, every frame index the task needs, in one pass per file."""
        wanted: dict[str, set[int]] = {}
        for ref in refs:
            if ref.codec == "mp4-frame":
                if ref.frame_index is None:
                    raise DecodeError(f"{ref.path}: an mp4-frame reference needs a frame_index")
                wanted.setdefault(ref.path, set()).add(int(ref.frame_index))
        for path, indices in sorted(wanted.items()):
            try:
                frames = decode_video_frames(self.resolve(path), indices)
            except DecodeError as error:
                self._video_errors[path] = str(error)
                continue
            for index, frame in frames.items():
                self._videos[(path, index)] = frame

    def source_sha256(self, ref: ImageRef, data: bytes | None = None) -> str:
        """sha256 of the native item: the zip member's bytes, else the whole file (hashed once)."""
        if ref.member is not None:
            return sha256_bytes(data if data is not None else self.read_bytes(ref))
        key = str(self.resolve(ref.path))
        if key not in self._hashes:
            self._hashes[key] = sha256_bytes(data) if data is not None else sha256_file(Path(key))
        return self._hashes[key]

    def decode(self, ref: ImageRef) -> tuple[np.ndarray, str]:
        """``(H, W, 3)`` float32 scene-linear RGB of ``ref`` and the sha256 of its native item."""
        where = ref.label
        if ref.codec == "mp4-frame":
            if ref.path in self._video_errors:
                raise DecodeError(self._video_errors[ref.path])
            key = (ref.path, int(ref.frame_index if ref.frame_index is not None else -1))
            if key not in self._videos:
                self.prefetch_videos([ref])
                if ref.path in self._video_errors:
                    raise DecodeError(self._video_errors[ref.path])
            codes = self._videos.pop(key)  # each frame is used once: free it
            return codes_to_linear(codes, "mp4-frame", where), self.source_sha256(ref)
        data = self.read_bytes(ref)
        return decode_bytes(data, ref.codec, where), self.source_sha256(ref, data)

    def decode_alpha(self, ref: ImageRef) -> np.ndarray:
        """``(H, W)`` float32 alpha in [0, 1] of an alpha-map reference."""
        data = self.read_bytes(ref)
        if ref.codec == "exr-linear":
            return decode_bytes(data, ref.codec, ref.label)[:, :, 0]
        return decode_alpha_bytes(data, ref.label)

    def close(self) -> None:
        for archive in self._zips.values():
            archive.close()
        self._zips.clear()
        self._videos.clear()

    def __enter__(self) -> TaskDecoder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def apply_colour_calibration(image_linear: np.ndarray, calibration: ColourCalibration) -> np.ndarray:
    """Apply ``calibration`` to ``(H, W, 3)`` linear RGB; returns float32 linear RGB clipped at 0.

    ``"linear"``: ``M @ (rgb - black) + offset`` on scene-linear values. ``"display"``: the same on the
    sRGB-encoded values (clipped to [0, 1] as the dataset's own loaders do), then decoded to linear.
    """

    identity = (
        np.array_equal(calibration.matrix, np.eye(3))
        and not np.any(calibration.black)
        and not np.any(calibration.offset)
    )
    if identity:
        image = image_linear.astype(np.float32, copy=False)
        # Decoded 8/16-bit codes are never negative: a min (one read) is 4x cheaper than a clip that
        # writes a new full-size image, and gives the same array when nothing is below 0.
        return image if image.min() >= 0.0 else np.maximum(image, 0.0)
    black = np.asarray(calibration.black, dtype=np.float64)
    offset = np.asarray(calibration.offset, dtype=np.float64)
    if calibration.space == "display":
        encoded = np.asarray(linear_to_srgb(np.clip(image_linear, 0.0, 1.0)), dtype=np.float32)
        corrected = apply_ccm(encoded, calibration.matrix, offset, black_level=black)
        return np.asarray(srgb_to_linear(np.clip(corrected, 0.0, 1.0)), dtype=np.float32)
    corrected = apply_ccm(
        image_linear.astype(np.float32, copy=False), calibration.matrix, offset, black_level=black
    )
    return np.maximum(corrected, 0.0).astype(np.float32, copy=False)
