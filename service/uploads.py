"""Uploads: a streamed multipart parser that writes file parts to disk against size limits, then content checks.

The body is parsed as it arrives (python-multipart's streaming parser); the ``video`` part goes straight to
``dest/video.upload`` and the request fails with 413 the moment it passes the limit. Files are never stored under
the client's filename, and a filename with a path in it is refused (400). After the body: the video's first bytes
must be a known video container (sniffed, 415 otherwise), then the whole stream is test-decoded by the engine's
reader (``agg.io.video.read_video``, strict) so empty, truncated and undecodable files are refused (422) before
anything is queued.
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

from python_multipart.multipart import MultipartParser, parse_options_header

from service.errors import ApiError

FILE_PARTS = ("video", "calibration")
TEXT_FIELDS = ("preset", "intrinsics", "max_frames")
MAX_FIELD_BYTES = 4096
MAX_CALIBRATION_BYTES = 256 * 1024
MAX_PARTS = 16
MULTIPART_OVERHEAD = 1 << 20  # headers, boundaries and text fields on top of the video limit


@dataclass
class SavedPart:
    path: Path
    size: int = 0
    filename: str | None = None


@dataclass
class ReceivedForm:
    fields: dict[str, str] = field(default_factory=dict)
    files: dict[str, SavedPart] = field(default_factory=dict)


def check_filename(name: str | None) -> None:
    """Refuse (400) a client filename that names a path: separators, '.', '..', NUL or control characters."""
    if name is None:
        return
    bad = ("/" in name or "\\" in name or name in (".", "..") or any(ord(c) < 32 for c in name)
           or PurePosixPath(name).name != name or len(name) > 255)
    if bad:
        raise ApiError(400, "invalid_filename", "the part's filename must be a plain file name (no path, no '..'); "
                                                "it is only kept as a label, never used to store the file")


class _FormSink:
    """Callbacks of the streaming parser: headers per part, text fields in memory, files to disk."""

    def __init__(self, dest: Path, video_limit: int):
        self.dest, self.video_limit = dest, video_limit
        self.form = ReceivedForm()
        self.parts, self.ended = 0, False
        self._hname, self._hval, self._headers = b"", b"", {}
        self._name, self._file, self._fh, self._text, self._limit = None, None, None, bytearray(), 0

    def on_part_begin(self) -> None:
        self.parts += 1
        if self.parts > MAX_PARTS:
            raise ApiError(400, "too_many_parts", f"at most {MAX_PARTS} form parts")
        self._headers = {}

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._hname += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._hval += data[start:end]

    def on_header_end(self) -> None:
        self._headers[self._hname.decode("latin-1").strip().lower()] = self._hval.decode("latin-1").strip()
        self._hname, self._hval = b"", b""

    def on_headers_finished(self) -> None:
        disp, params = parse_options_header(self._headers.get("content-disposition", ""))
        raw_name = params.get(b"name")
        if disp != b"form-data" or raw_name is None:
            raise ApiError(400, "malformed_multipart", "every part needs 'Content-Disposition: form-data; name=...'")
        name = raw_name.decode("utf-8", "replace")
        if name in self.form.fields or name in self.form.files:
            raise ApiError(400, "duplicate_field", f"the form field {name!r} appears twice")
        filename = params.get(b"filename")
        filename = filename.decode("utf-8", "replace") if filename is not None else None
        if name in FILE_PARTS:
            check_filename(filename)
            path = self.dest / f"{name}.upload"
            self._file = SavedPart(path, 0, filename)
            self._fh = open(path, "wb")  # noqa: SIM115 - closed in on_part_end / close()
            self._limit = self.video_limit if name == "video" else MAX_CALIBRATION_BYTES
        elif name in TEXT_FIELDS:
            self._file, self._text, self._limit = None, bytearray(), MAX_FIELD_BYTES
        else:
            raise ApiError(422, "unknown_field", f"unknown form field {name!r}; the fields are "
                                                 f"{', '.join(FILE_PARTS + TEXT_FIELDS)}")
        self._name = name

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        n = end - start
        if self._file is not None:
            self._file.size += n
            if self._file.size > self._limit:
                what = "video" if self._name == "video" else "calibration file"
                raise ApiError(413, "upload_too_large", f"the {what} is larger than the limit of {self._limit} bytes")
            self._fh.write(data[start:end])
        else:
            if len(self._text) + n > self._limit:
                raise ApiError(413, "field_too_large", f"form field {self._name!r} is over {self._limit} bytes")
            self._text += data[start:end]

    def on_part_end(self) -> None:
        if self._file is not None:
            self._fh.close()
            self._fh = None
            self.form.files[self._name] = self._file
        elif self._name is not None:
            try:
                self.form.fields[self._name] = self._text.decode("utf-8")
            except UnicodeDecodeError:
                raise ApiError(400, "malformed_field", f"form field {self._name!r} is not UTF-8 text") from None
        self._name, self._file = None, None

    def on_end(self) -> None:
        self.ended = True

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


async def receive_form(request, dest: Path, video_limit: int) -> ReceivedForm:
    """Stream a multipart/form-data body into ``dest`` (created). Raises ApiError (400/413/415/422)."""
    ctype, params = parse_options_header(request.headers.get("content-type"))
    boundary = params.get(b"boundary")
    if ctype != b"multipart/form-data" or not boundary:
        raise ApiError(415, "expected_multipart", "send multipart/form-data with a 'video' file part and a 'preset' "
                                                  "field")
    length = request.headers.get("content-length")
    if length is not None and length.isdigit() and int(length) > video_limit + MULTIPART_OVERHEAD:
        raise ApiError(413, "upload_too_large", f"the body ({length} bytes) is larger than the limit of "
                                                f"{video_limit} bytes for the video")
    dest.mkdir(parents=True, exist_ok=True)
    sink = _FormSink(dest, video_limit)
    callbacks = {name: getattr(sink, name) for name in
                 ("on_part_begin", "on_header_field", "on_header_value", "on_header_end", "on_headers_finished",
                  "on_part_data", "on_part_end", "on_end")}
    total, body_limit = 0, video_limit + MULTIPART_OVERHEAD
    try:
        parser = MultipartParser(boundary, callbacks)
        async for chunk in request.stream():
            total += len(chunk)
            if total > body_limit:
                raise ApiError(413, "upload_too_large", f"the body is larger than the limit of {video_limit} bytes "
                                                        "for the video")
            if chunk:
                parser.write(chunk)
        parser.finalize()
    except ApiError:
        raise
    except ValueError as exc:  # python-multipart's parse errors (FormParserError is a ValueError)
        raise ApiError(400, "malformed_multipart", f"the multipart body could not be parsed: {exc}") from None
    finally:
        sink.close()
    if not sink.ended:
        raise ApiError(400, "malformed_multipart", "the multipart body ended before its closing boundary")
    return sink.form


def parse_intrinsics(text: str) -> list[float]:
    """'fx,fy,cx,cy' (source pixels) -> [fx, fy, cx, cy]; 422 unless 4 finite numbers with fx, fy > 0."""
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 4 or not all(math.isfinite(v) for v in vals) or vals[0] <= 0 or vals[1] <= 0:
        raise ApiError(422, "invalid_intrinsics", "intrinsics must be 'fx,fy,cx,cy': four finite numbers in source "
                                                  "pixels with fx > 0 and fy > 0")
    return vals


def parse_max_frames(text: str, limit: int) -> int:
    if not text.strip().isdigit() or not 2 <= int(text) <= limit:
        raise ApiError(422, "invalid_max_frames", f"max_frames must be an integer in [2, {limit}]")
    return int(text)


def check_calibration(part: SavedPart) -> Path:
    """Validate an OpenCV calibration file (K 3x3, dist; YAML/XML/JSON) and give it its format's suffix."""
    from agg.io.video import load_opencv_calibration

    head = part.path.read_bytes()[:64].lstrip()
    suffix = ".xml" if head.startswith(b"<") else ".json" if head.startswith(b"{") else ".yml"
    path = part.path.with_name("calibration" + suffix)
    part.path.replace(path)
    part.path = path
    try:
        K, dist, _ = load_opencv_calibration(path)  # noqa: N806
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not (abs(K) < 1e7).all():
            raise ValueError("K needs positive focal lengths")
    except Exception as exc:  # noqa: BLE001 - OpenCV raises cv2.error on garbage; all of it is the client's
        raise ApiError(422, "invalid_calibration", f"the calibration file is not an OpenCV file with a 3x3 'K' and "
                                                   f"a 'dist' vector: {str(exc)[:200]}") from None
    return path


CONTAINERS = {"mp4": ".mp4", "mkv": ".mkv", "avi": ".avi", "ts": ".ts", "mpg": ".mpg", "flv": ".flv", "ogg": ".ogv"}


def sniff_container(head: bytes) -> str | None:
    """The video container named by a file's first bytes (>= 376 of them for MPEG-TS), or None."""
    if len(head) >= 8 and head[4:8] in (b"ftyp", b"moov", b"mdat", b"wide", b"free", b"skip", b"pnot"):
        return "mp4"
    if head.startswith(b"\x1a\x45\xdf\xa3"):
        return "mkv"
    if head.startswith(b"RIFF") and head[8:12] == b"AVI ":
        return "avi"
    if len(head) > 188 and head[0] == 0x47 and head[188] == 0x47:
        return "ts"
    if head.startswith(b"\x00\x00\x01\xba"):
        return "mpg"
    if head.startswith(b"FLV"):
        return "flv"
    if head.startswith(b"OggS"):
        return "ogg"
    return None


def mp4_cut_box(path: Path) -> str | None:
    """For an MP4/MOV: a message when a top-level box runs past the end of the file (the file was cut), else None."""
    import struct

    size = path.stat().st_size
    with open(path, "rb") as fh:
        pos = 0
        while pos + 8 <= size:
            fh.seek(pos)
            n, kind = struct.unpack(">I4s", fh.read(8))
            if n == 1:
                head = fh.read(8)
                if len(head) < 8:
                    return "the file ends inside a box header"
                n = struct.unpack(">Q", head)[0]
            elif n == 0:
                return None  # the last box extends to the end of the file by definition
            if n < 8:
                return None  # not a box structure we can judge; the decoder decides
            if pos + n > size:
                name = kind.decode("latin-1", "replace")
                return f"the file ends inside its '{name}' box ({size - pos} of {n} bytes present)"
            pos += n
    return None


def inspect_video(part: SavedPart, max_source_pixels: int | None = None) -> dict:
    """Sniff and test-decode the uploaded video (strict: a truncated file is refused); renames it
    ``video.<ext>`` and returns {container, frames, width, height, fps, bytes}. Raises ApiError 415/422."""
    import warnings

    from agg.io import errors as E  # noqa: N812
    from agg.io.video import IngestConfig, read_video

    if part.size == 0:
        raise ApiError(422, "empty_upload", "the video part is empty (0 bytes)")
    with open(part.path, "rb") as fh:
        head = fh.read(400)
    container = sniff_container(head)
    if container is None:
        raise ApiError(415, "not_a_video", "the upload is not a video container (MP4/MOV, MKV/WebM, AVI, MPEG-TS, "
                                           "MPEG-PS, FLV or Ogg)")
    path = part.path.with_name("video" + CONTAINERS[container])
    part.path.replace(path)
    part.path = path
    cut = mp4_cut_box(path) if container == "mp4" else None
    if cut:
        raise ApiError(422, "truncated_video", f"the video is truncated: {cut}; upload the complete file")
    cfg = IngestConfig(width=16, strict=True, dtype="uint8", min_frames=2)
    if max_source_pixels:
        cfg.max_source_pixels = max_source_pixels
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = read_video(path, cfg)
    except E.TruncatedVideoError as exc:
        raise ApiError(422, "truncated_video", f"the video is truncated: decoding stopped at source frame "
                                               f"{exc.frame_index}; upload the complete file") from None
    except E.NoDecodableFramesError as exc:
        code = "truncated_video" if "truncated" in str(exc) else "undecodable_video"
        raise ApiError(422, code, _client_message(exc, path)) from None
    except E.NotAVideoError as exc:
        raise ApiError(415, "not_a_video", _client_message(exc, path)) from None
    except E.TooManyPixelsError as exc:
        raise ApiError(422, "resolution_too_large", _client_message(exc, path)) from None
    except E.TooFewFramesError as exc:
        raise ApiError(422, "too_few_frames", _client_message(exc, path)) from None
    except Exception as exc:  # noqa: BLE001 - any decoder failure is a property of the uploaded bytes
        raise ApiError(422, "invalid_video", f"the video could not be decoded: {_client_message(exc, path)}") from None
    return {"container": container, "frames": int(len(res.frames)), "width": int(res.source_size[0]),
            "height": int(res.source_size[1]), "fps": res.source_fps, "bytes": part.size}


def _client_message(exc: Exception, path: Path) -> str:
    """The engine's message without the server-side path."""
    return str(exc).replace(str(path), "video")[:500]


def discard(dest: Path) -> None:
    shutil.rmtree(dest, ignore_errors=True)
