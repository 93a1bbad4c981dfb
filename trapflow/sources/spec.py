"""Parse `--source KIND:ARGS` strings into (kind, uri) for SourceConfig.

Each kind says what its ARGS look like; errors name the bad part so click can show them.
"""

from __future__ import annotations

from trapflow.errors import ConfigError

#: kind -> the ARGS it expects, shown in errors and help
SPEC_FORMS: dict[str, str] = {
    "synthetic": "synthetic (no arguments)",
    "video": "video:LEFT,RIGHT or video:SIDE_BY_SIDE",
    "images": "images:DIR (left/ and right/, or KITTI image_0/ image_1/)",
    "v4l2": "v4l2:/dev/videoA,/dev/videoB (or camera indices 0,1)",
    "picamera2": "picamera2:0,1",
    "gst": "gst:LEFT_PIPELINE,RIGHT_PIPELINE (each ending in appsink)",
    "replay": "replay:PATH (a trapflow recording or a ROS 2 bag)",
}


def _fail(text: str, why: str) -> ConfigError:
    forms = "; ".join(SPEC_FORMS.values())
    return ConfigError(f"source {text!r}: {why}; expected one of: {forms}")


def split_pair(args: str) -> tuple[str, str]:
    """Split `A,B` into two non-empty parts (single comma)."""
    parts = [p.strip() for p in args.split(",")]
    if len(parts) != 2 or not all(parts):
        raise ValueError(f"expected two comma-separated parts, got {len(parts)} in {args!r}")
    return parts[0], parts[1]


def split_gst(args: str) -> tuple[str, str]:
    """Split two GStreamer pipelines; caps inside them contain commas, so split after appsink."""
    idx = args.find("appsink")
    while idx >= 0:
        comma = args.find(",", idx)
        if comma < 0:
            break
        # appsink properties are space-separated, so the first comma after it ends the pipeline
        # unless the text between is a caps string (which would contain '/').
        between = args[idx:comma]
        if "!" not in between and "/" not in between:
            left, right = args[:comma].strip(), args[comma + 1 :].strip()
            if left and right:
                return left, right
        idx = args.find("appsink", comma)
    return split_pair(args)


def parse_source_spec(text: str) -> tuple[str, str]:
    """`KIND:ARGS` -> (kind, uri). The uri keeps ARGS as given (paths are checked at open)."""
    kind, sep, args = text.partition(":")
    kind = kind.strip().lower()
    if kind not in SPEC_FORMS:
        raise _fail(text, f"unknown kind {kind!r}")
    args = args.strip()
    if kind == "synthetic":
        if args:
            raise _fail(text, f"synthetic takes no arguments, got {args!r}")
        return kind, ""
    if not sep or not args:
        raise _fail(text, f"{kind} needs arguments after ':'")
    try:
        if kind in ("v4l2", "picamera2"):
            split_pair(args)
        elif kind == "gst":
            split_gst(args)
        elif kind == "video" and "," in args:
            split_pair(args)
    except ValueError as exc:
        raise _fail(text, str(exc)) from None
    if kind == "picamera2":
        for part in split_pair(args):
            if not part.isdigit():
                raise _fail(text, f"picamera2 expects camera numbers, got {part!r}")
    return kind, args
