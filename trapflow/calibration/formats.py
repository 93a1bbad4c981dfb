"""Readers (and a camera_info writer) for the stereo calibration formats people bring.

Understood: trapflow's own YAML; plain K1/D1/K2/D2/R/T YAML; a ROS camera_info pair
(`camera_calibration` output, plumb_bob / rational_polynomial / equidistant, and its
fisheye mode's `plumb_bob` with 4 coefficients) or its oST text file; a Kalibr camchain
(cam0 + cam1); OpenCV FileStorage YAML/XML (stereo_calib.cpp's intrinsics + extrinsics,
stereoRectify's output, cv::fisheye::stereoCalibrate's output). Except for trapflow's own
files, the rectification is computed here from K/D/R/T (calibration.rectify) and,
where the file carries R1/R2, checked against them. Errors name the file, the field and
FORMATS.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, cast

import cv2
import msgspec
import numpy as np
import yaml

from trapflow.calibration.model import StereoCalibration, from_extrinsics
from trapflow.calibration.rectify import MODELS, Model
from trapflow.errors import ConfigError, yaml_problem

log = logging.getLogger(__name__)

FORMATS = ("trapflow YAML; plain K1/D1/K2/D2/R/T YAML with image_width/image_height; "
           "a ROS camera_info pair (LEFT.yaml,RIGHT.yaml or a folder holding both) or "
           "ost.txt; "
           "a Kalibr camchain with cam0 and cam1; OpenCV FileStorage YAML/XML with "
           "K1|M1, D1, K2|M2, D2, R, T (one file, or intrinsics,extrinsics)")
SUFFIXES = (".yaml", ".yml", ".xml", ".json", ".txt", ".ini")
# A file's own rectifying rotations must match the ones computed from its R and T; they
# are written with 6 decimals by ROS, so 1e-3 only catches a real contradiction.
ROTATION_TOLERANCE = 1e-3
_ROS_MODELS: dict[str, Model] = {"plumb_bob": "pinhole", "rational_polynomial": "pinhole",
                                 "equidistant": "fisheye", "fisheye": "fisheye"}
_KALIBR_MODELS: dict[str, Model] = {"radtan": "pinhole", "equidistant": "fisheye",
                                    "none": "pinhole"}


def fail(where: str | Path, what: str) -> ConfigError:
    """A ConfigError naming the file, what is wrong and the formats understood."""
    return ConfigError(f"calibration {where}: {what} (formats understood: {FORMATS})")


def parse_trapflow(data: dict[str, object], where: str) -> StereoCalibration:
    """trapflow's own fields, or plain K1/D1/K2/D2/R/T (+ image size) rectified here."""
    if "R1" not in data and all(k in data for k in ("K1", "D1", "K2", "D2", "R", "T")):
        return _from_plain(data, where)
    try:
        return msgspec.convert(data, StereoCalibration)
    except msgspec.ValidationError as exc:
        raise fail(where, str(exc).strip()) from None


def _from_plain(data: dict[str, object], where: str) -> StereoCalibration:
    for key in ("image_width", "image_height"):
        if not isinstance(data.get(key), int):
            raise fail(where, f"plain K1/D1/K2/D2/R/T needs {key} (an integer, pixels), "
                              f"got {data.get(key)!r}; add `image_width: W` and "
                              "`image_height: H`")
    size = (int(str(data["image_width"])), int(str(data["image_height"])))
    try:
        arrs = {k: np.asarray(data[k], np.float64) for k in ("K1", "D1", "K2", "D2", "R", "T")}
    except (TypeError, ValueError) as exc:
        raise fail(where, f"K1/D1/K2/D2/R/T must be numbers: {exc}") from None
    model = data.get("model") or guess_model(arrs["D1"].size)
    if model not in MODELS:
        raise fail(where, f"model: expected one of {', '.join(MODELS)}, got {model!r}")
    for name, shape in (("K1", (3, 3)), ("K2", (3, 3)), ("R", (3, 3))):
        if arrs[name].shape != shape:
            raise fail(where, f"field {name}: expected shape {shape}, got {arrs[name].shape}")
    if arrs["T"].size != 3:
        raise fail(where, f"field T: expected 3 numbers, got {arrs['T'].size}")
    try:
        return from_extrinsics(model=model, size=size,
                               k1=arrs["K1"], d1=arrs["D1"], k2=arrs["K2"], d2=arrs["D2"],
                               r=arrs["R"], t=arrs["T"])
    except (ValueError, cv2.error) as exc:
        raise fail(where, str(exc).strip()) from None


def guess_model(n_coefficients: int) -> Model:
    """The lens model a distortion vector implies when the file does not say it.

    Four coefficients are a fisheye's k1..k4: OpenCV's pinhole calibration always writes
    5, 8, 12 or 14, and ROS camera_calibration's fisheye mode writes 4 under `plumb_bob`.
    """
    return "fisheye" if n_coefficients == 4 else "pinhole"


def read_calibration(spec: str, image_size: tuple[int, int] | None = None) -> StereoCalibration:
    """One file, `A,B` or a folder (see module docstring) -> a complete StereoCalibration."""
    if "," in spec:
        parts = [Path(p.strip()) for p in spec.split(",")]
        if len(parts) != 2:
            raise fail(spec, f"expected LEFT,RIGHT (two files), got {len(parts)} names")
        return _from_docs([(p, load_doc(p)) for p in parts], spec, image_size)
    path = Path(spec)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in SUFFIXES)
        docs = []
        for p in files:
            try:
                docs.append((p, load_doc(p)))
            except ConfigError as exc:
                log.debug("calibration folder %s: skipping %s: %s", path, p.name, exc)
        if not docs:
            raise fail(path, f"no readable calibration file ({', '.join(SUFFIXES)}) in the folder")
        return _from_docs(docs, str(path), image_size)
    doc = load_doc(path)
    kind = classify(doc)
    if kind in ("ros", "opencv-intrinsics", "opencv-extrinsics"):
        partner = _partner(path, kind)
        if partner is not None:
            return _from_docs([(path, doc), (partner, load_doc(partner))],
                              f"{path},{partner}", image_size)
    return _from_docs([(path, doc)], str(path), image_size)


def load_doc(path: Path) -> dict[str, Any]:
    """A file's top-level fields: PyYAML for plain YAML, cv2.FileStorage for OpenCV's."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise ConfigError(f"cannot read calibration {path}: {exc.strerror}") from None
    head = text.lstrip()[:200]
    if head.startswith("# oST") or head.startswith("[image]"):
        return {"__ost__": parse_ost(text, path)}
    if head.startswith(("%YAML", "<?xml", "<opencv_storage")) or "!!opencv-matrix" in text:
        return _load_filestorage(path)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise fail(path, f"not valid YAML: {yaml_problem(exc)}") from None
    if not isinstance(data, dict):
        raise fail(path, f"expected a mapping of fields, got {type(data).__name__}")
    return data


def parse_ost(text: str, where: Path) -> list[dict[str, Any]]:
    """ROS camera_calibration's oST text: [image] width/height, then one [camera] section
    each (camera matrix, distortion, rectification, projection), as camera_info fields."""
    cams: list[dict[str, Any]] = []
    size: dict[str, int] = {}
    section, key = "", ""
    rows: list[list[float]] = []
    fields = {"camera matrix": "camera_matrix", "distortion": "distortion_coefficients",
              "rectification": "rectification_matrix", "projection": "projection_matrix"}

    def flush() -> None:
        if not key or not rows:
            return
        if section == "image":
            size[key] = int(rows[0][0])
        elif key in fields:
            cams[-1][fields[key]] = {"data": [v for row in rows for v in row]}

    for raw in text.splitlines() + [""]:
        line = raw.strip()
        if line.startswith("#"):
            continue
        try:
            values = [float(v) for v in line.split()] if line else []
        except ValueError:
            values = []
        if values:
            rows.append(values)
            continue
        flush()
        key, rows = "", []
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
            if section != "image":
                cams.append({"camera_name": section})
        elif line:
            key = line
    if "width" not in size or "height" not in size:
        raise fail(where, "oST file without [image] width and height")
    for cam in cams:
        n = len(cam.get("distortion_coefficients", {"data": []})["data"])
        cam.update(image_width=size["width"], image_height=size["height"],
                   distortion_model="rational_polynomial" if n == 8 else "plumb_bob")
    return cams


def _load_filestorage(path: Path) -> dict[str, Any]:
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise fail(path, f"OpenCV FileStorage cannot parse it: {str(exc).strip()[-160:]}") from None
    if not fs.isOpened():
        raise fail(path, "OpenCV FileStorage cannot open it")
    out: dict[str, Any] = {"__filestorage__": True}
    try:
        for key in fs.root().keys():  # noqa: SIM118 - a FileNode is not iterable
            node = fs.getNode(key)
            if node.isMap():
                mat = node.mat()
                if mat is not None:
                    out[key] = np.asarray(mat, np.float64)
            elif node.isSeq():
                items = [node.at(i) for i in range(node.size())]
                if all(it.isReal() or it.isInt() for it in items):
                    out[key] = np.array([it.real() for it in items], np.float64)
            elif node.isInt():
                out[key] = int(node.real())
            elif node.isReal():
                out[key] = float(node.real())
            elif node.isString():
                out[key] = node.string()
    finally:
        fs.release()
    return out


def classify(doc: dict[str, Any]) -> str:
    """ros, kalibr, kalibr-mono, opencv, opencv-intrinsics, opencv-extrinsics, trapflow, mono."""
    keys = set(doc)
    if "__ost__" in keys:
        return "ost"
    if "camera_matrix" in keys and "distortion_coefficients" in keys:
        return "ros"
    if "cam0" in keys:
        return "kalibr" if "cam1" in keys else "kalibr-mono"
    has_k = bool({"K1", "M1"} & keys) and bool({"K2", "M2"} & keys)
    has_rt = {"R", "T"} <= keys
    if doc.get("__filestorage__"):
        if has_k and has_rt:
            return "opencv"
        if has_k and {"D1", "D2"} <= keys:
            return "opencv-intrinsics"
        if has_rt:
            return "opencv-extrinsics"
    elif has_k or {"R1", "version", "image_width"} & keys:
        return "trapflow"
    if {"camera_matrix", "cameraMatrix", "K"} & keys:
        return "mono"
    return "unknown"


# What a lone file of these kinds holds, and what a stereo calibration needs besides.
_HALF_A_PAIR = {
    "kalibr-mono": "a Kalibr camchain with one camera (cam0 only); a stereo pair is needed: "
                   "a camchain with cam0 and cam1 (T_cn_cnm1)",
    "opencv-intrinsics": "OpenCV intrinsics (M1 D1 M2 D2) without R and T; give "
                         "intrinsics.yml,extrinsics.yml or put extrinsics.yml beside it",
    "opencv-extrinsics": "OpenCV extrinsics (R T) without K1/M1, D1, K2/M2, D2; give "
                         "intrinsics.yml,extrinsics.yml or put intrinsics.yml beside it",
    "mono": "a single camera's calibration; a stereo pair is needed "
            "(missing K1/M1, K2/M2, R, T)",
}


def _partner(path: Path, kind: str) -> Path | None:
    """The other file of a two-file calibration next to `path`, when one is found."""
    name = path.name
    if kind == "ros":
        for a, b in (("left", "right"), ("right", "left"), ("Left", "Right"),
                     ("Right", "Left"), ("LEFT", "RIGHT"), ("RIGHT", "LEFT")):
            if a in name:
                i = name.rfind(a)
                other = path.with_name(name[:i] + b + name[i + len(a):])
                return other if other.is_file() else None
        return None
    want = "extrinsics" if kind == "opencv-intrinsics" else "intrinsics"
    for suffix in (path.suffix, ".yml", ".yaml", ".xml"):
        other = path.with_name(want + suffix)
        if other.is_file():
            return other
    return None


def _from_docs(docs: list[tuple[Path, dict[str, Any]]], where: str,
               image_size: tuple[int, int] | None) -> StereoCalibration:
    kinds = {p: classify(d) for p, d in docs}
    complete = [(p, d) for p, d in docs if kinds[p] in ("trapflow", "kalibr", "opencv")]
    ros = [(p, d) for p, d in docs if kinds[p] == "ros"]
    intr = [(p, d) for p, d in docs if kinds[p] == "opencv-intrinsics"]
    extr = [(p, d) for p, d in docs if kinds[p] == "opencv-extrinsics"]
    if len(ros) > 2:  # a folder with other cameras' files: the pair is named left/right
        ros = [(p, d) for p, d in ros if "left" in p.name.lower() or "right" in p.name.lower()]
    if len(complete) == 1 and len(ros) != 2:
        p, d = complete[0]
        kind = kinds[p]
        if kind == "trapflow":
            return parse_trapflow(d, str(p))
        if kind == "kalibr":
            return read_kalibr(d, p)
        return read_opencv(d, p, image_size)
    ost = [(p, c) for p, d in docs if kinds[p] == "ost" for c in d["__ost__"]]
    if len(ost) == 2 and not ros:
        ros = ost
    if len(ros) == 2:
        log.info("calibration %s: using the camera_info pair %s, %s", where,
                 ros[0][0].name, ros[1][0].name)
        return read_ros_pair(ros[0], ros[1])
    if len(intr) == 1 and len(extr) == 1:
        merged = {**extr[0][1], **intr[0][1]}
        return read_opencv(merged, Path(f"{intr[0][0]},{extr[0][0]}"), image_size)
    if len(docs) == 1:
        p, d = docs[0]
        kind = kinds[p]
        if kind == "ros":
            raise fail(p, f"one camera's camera_info (camera_name {d.get('camera_name')!r}); "
                          "a stereo pair is needed: give LEFT.yaml,RIGHT.yaml or a folder "
                          "holding both (a name with 'left' finds its 'right' sibling)")
        if kind == "ost":
            raise fail(p, f"an oST file with {len(d['__ost__'])} camera(s); a stereo pair "
                          "(two camera sections) is needed")
        if kind in _HALF_A_PAIR:
            raise fail(p, _HALF_A_PAIR[kind])
        raise fail(p, f"format not recognised (fields: {', '.join(sorted(map(str, d))[:12])})")
    found = ", ".join(f"{p.name} ({kinds[p]})" for p, _ in docs)
    raise fail(where, f"expected one stereo file or one pair of files, found {found}")


def _matrix(value: Any, shape: tuple[int, ...], where: str | Path, field: str) -> np.ndarray:
    """A numeric field of the given shape: a ROS {rows, cols, data} mapping or a list."""
    if isinstance(value, dict) and "data" in value:
        value = value["data"]
    try:
        arr = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise fail(where, f"field {field}: expected numbers, got {value!r}") from None
    if arr.size != int(np.prod(shape)):
        raise fail(where, f"field {field}: expected {'x'.join(map(str, shape))} numbers, "
                          f"got {arr.size}")
    return arr.reshape(shape)


def _vector(value: Any, where: str | Path, field: str) -> np.ndarray:
    """A flat numeric field of any length (a ROS {rows, cols, data} mapping or a list)."""
    if isinstance(value, dict) and "data" in value:
        value = value["data"]
    try:
        return np.asarray(value if value is not None else [], np.float64).ravel()
    except (TypeError, ValueError):
        raise fail(where, f"field {field}: expected numbers, got {value!r}") from None


def _require(doc: dict[str, Any], where: str | Path, *fields: str) -> None:
    for f in fields:
        if f not in doc:
            raise fail(where, f"missing field {f!r}")


def _ros_camera(doc: dict[str, Any], p: Path) -> dict[str, Any]:
    _require(doc, p, "image_width", "image_height", "camera_matrix", "distortion_model",
             "distortion_coefficients", "rectification_matrix", "projection_matrix")
    d = _vector(doc["distortion_coefficients"], p, "distortion_coefficients")
    name = str(doc["distortion_model"])
    if name not in _ROS_MODELS:
        raise fail(p, f"distortion_model: expected one of {', '.join(_ROS_MODELS)}, got {name!r}")
    model = _ROS_MODELS[name]
    if name == "plumb_bob" and d.size == 4:
        model = guess_model(4)
        log.warning("calibration %s: distortion_model plumb_bob with 4 coefficients read as "
                    "fisheye (equidistant k1..k4), as ROS camera_calibration's fisheye mode "
                    "writes it; say `distortion_model: equidistant` to silence this", p)
    return {
        "size": (int(doc["image_width"]), int(doc["image_height"])),
        "K": _matrix(doc["camera_matrix"], (3, 3), p, "camera_matrix"),
        "D": d, "model": model,
        "R": _matrix(doc["rectification_matrix"], (3, 3), p, "rectification_matrix"),
        "P": _matrix(doc["projection_matrix"], (3, 4), p, "projection_matrix"),
    }


def read_ros_pair(a: tuple[Path, dict[str, Any]],
                  b: tuple[Path, dict[str, Any]]) -> StereoCalibration:
    """Two camera_info files; the right one is the one whose P carries Tx = -fx * baseline."""
    cams = [(p, _ros_camera(d, p)) for p, d in (a, b)]
    cams.sort(key=lambda c: c[1]["P"][0, 3] != 0)  # left first
    (pl, left), (pr, right) = cams
    where = f"{pl},{pr}"
    if left["P"][0, 3] != 0 or right["P"][0, 3] == 0:
        raise fail(where, "projection_matrix: expected P[0][3] = 0 in the left file and "
                          "-fx * baseline in the right one; got "
                          f"{left['P'][0, 3]} and {right['P'][0, 3]}")
    if left["size"] != right["size"]:
        raise fail(where, f"image sizes differ: {left['size']} and {right['size']}")
    if left["model"] != right["model"]:
        raise fail(where, f"lens models differ: {left['model']} and {right['model']}")
    # The files give each camera's rectifying rotation and the rectified right camera's
    # offset; the extrinsics follow: X_r = R2^T (R1 X_l + t_rect).
    p2 = right["P"]
    t_rect = np.array([p2[0, 3] / p2[0, 0], p2[1, 3] / p2[1, 1], 0.0])
    r = right["R"].T @ left["R"]
    t = right["R"].T @ t_rect
    calib = _complete(left["model"], left["size"], left["K"], left["D"], right["K"],
                      right["D"], r, t, where)
    _check_rotations(calib, left["R"], right["R"], where)
    return calib


def read_kalibr(doc: dict[str, Any], p: Path) -> StereoCalibration:
    """cam0 and cam1 of a Kalibr camchain: intrinsics [fu fv pu pv], T_cn_cnm1 of cam1."""
    cams: list[dict[str, Any]] = []
    for name in ("cam0", "cam1"):
        cam = doc[name]
        if not isinstance(cam, dict):
            raise fail(p, f"{name}: expected a mapping, got {type(cam).__name__}")
        _require(cam, f"{p} {name}", "camera_model", "intrinsics", "distortion_model",
                 "distortion_coeffs", "resolution")
        if cam["camera_model"] != "pinhole":
            raise fail(p, f"{name}.camera_model: expected pinhole, got {cam['camera_model']!r}")
        dm = str(cam["distortion_model"])
        if dm not in _KALIBR_MODELS:
            raise fail(p, f"{name}.distortion_model: expected one of "
                          f"{', '.join(_KALIBR_MODELS)}, got {dm!r}")
        fu, fv, pu, pv = _matrix(cam["intrinsics"], (4,), p, f"{name}.intrinsics")
        coeffs = _vector(cam["distortion_coeffs"] or [0, 0, 0, 0], p, f"{name}.distortion_coeffs")
        model = _KALIBR_MODELS[dm]
        d = coeffs if model == "fisheye" else np.r_[coeffs[:4], np.zeros(5 - coeffs[:4].size)]
        w, h = _matrix(cam["resolution"], (2,), p, f"{name}.resolution")
        cams.append({"K": np.array([[fu, 0, pu], [0, fv, pv], [0, 0, 1]]), "D": d,
                     "model": model, "size": (int(w), int(h))})
    if "T_cn_cnm1" not in doc["cam1"]:
        raise fail(p, "cam1: missing field 'T_cn_cnm1' (cam0 to cam1 transform)")
    tf = _matrix(doc["cam1"]["T_cn_cnm1"], (4, 4), p, "cam1.T_cn_cnm1")
    c0, c1 = cams
    if c0["size"] != c1["size"] or c0["model"] != c1["model"]:
        raise fail(p, f"cam0 and cam1 differ: {c0['size']} {c0['model']} against "
                      f"{c1['size']} {c1['model']}; trapflow needs one size and lens model")
    return _complete(c0["model"], c0["size"], c0["K"], c0["D"], c1["K"], c1["D"],
                     tf[:3, :3], tf[:3, 3], str(p))


def read_opencv(doc: dict[str, Any], p: Path, image_size: tuple[int, int] | None
                ) -> StereoCalibration:
    """OpenCV FileStorage fields: K1|M1, D1, K2|M2, D2, R, T (+ R1 R2 P1 P2 Q, size)."""
    k1 = doc.get("K1", doc.get("M1"))
    k2 = doc.get("K2", doc.get("M2"))
    _require({**doc, "K1": k1, "K2": k2} if k1 is not None and k2 is not None else doc, p,
             "K1", "K2", "D1", "D2", "R", "T")
    size = image_size or _opencv_size(doc)
    if size is None:
        raise fail(p, "no image size in the file (image_width/image_height or imageSize); "
                      "add `image_width: W` and `image_height: H` to it, or pass image_size")
    d1 = _vector(doc["D1"], p, "D1")
    model = doc.get("model") or doc.get("distortion_model") or guess_model(d1.size)
    model = {"equidistant": "fisheye", "plumb_bob": "pinhole", "radtan": "pinhole"}.get(
        model, model)
    if model not in ("pinhole", "fisheye"):
        raise fail(p, f"model: expected pinhole or fisheye, got {model!r}")
    model = cast(Model, model)
    r = _matrix(doc["R"], (3, 3), p, "R") if np.size(doc["R"]) == 9 else \
        cv2.Rodrigues(_matrix(doc["R"], (3,), p, "R"))[0]
    calib = _complete(model, size, _matrix(k1, (3, 3), p, "K1"), d1,
                      _matrix(k2, (3, 3), p, "K2"), _vector(doc["D2"], p, "D2"),
                      r, _matrix(doc["T"], (3,), p, "T"), str(p))
    if "R1" in doc and "R2" in doc:
        _check_rotations(calib, _matrix(doc["R1"], (3, 3), p, "R1"),
                         _matrix(doc["R2"], (3, 3), p, "R2"), str(p))
    return calib


def _opencv_size(doc: dict[str, Any]) -> tuple[int, int] | None:
    for wk, hk in (("image_width", "image_height"), ("width", "height")):
        if isinstance(doc.get(wk), (int, float)) and isinstance(doc.get(hk), (int, float)):
            return int(doc[wk]), int(doc[hk])
    for key in ("imageSize", "image_size"):
        if key in doc and np.size(doc[key]) == 2:
            w, h = np.asarray(doc[key]).ravel()
            return int(w), int(h)
    return None


def _complete(model: Model, size: tuple[int, int], k1: np.ndarray, d1: np.ndarray,
              k2: np.ndarray, d2: np.ndarray, r: np.ndarray, t: np.ndarray,
              where: str) -> StereoCalibration:
    try:
        return from_extrinsics(model=model, size=size, k1=k1, d1=d1, k2=k2, d2=d2, r=r, t=t)
    except (ValueError, cv2.error) as exc:
        raise fail(where, str(exc).strip()) from None


def _check_rotations(calib: StereoCalibration, r1: np.ndarray, r2: np.ndarray,
                     where: str) -> None:
    """The file's own rectifying rotations must be the ones its R and T imply."""
    for name, given in (("R1", r1), ("R2", r2)):
        err = float(np.abs(calib.arr(name) - given).max())
        if err > ROTATION_TOLERANCE:
            raise fail(where, f"{name} in the file differs from the rectification its "
                              f"R and T imply by {err:.4f} (tolerance {ROTATION_TOLERANCE}); "
                              "the file contradicts itself")


def write_camera_info(calib: StereoCalibration, left: Path, right: Path,
                      names: tuple[str, str] = ("left", "right")) -> None:
    """The calibration as a ROS camera_info pair, as `camera_calibration` writes it."""
    if calib.model == "fisheye":
        dist_model = "equidistant"
    else:
        dist_model = "rational_polynomial" if len(calib.D1) >= 8 else "plumb_bob"
    for path, name, k, d, r, p in ((left, names[0], "K1", "D1", "R1", "P1"),
                                   (right, names[1], "K2", "D2", "R2", "P2")):
        dist = [float(v) for v in calib.arr(d).ravel()]
        if dist_model == "plumb_bob" and len(dist) < 5:
            dist += [0.0] * (5 - len(dist))
        doc = {
            "image_width": calib.image_width, "image_height": calib.image_height,
            "camera_name": name,
            "camera_matrix": {"rows": 3, "cols": 3, "data": _flat(calib.arr(k))},
            "distortion_model": dist_model,
            "distortion_coefficients": {"rows": 1, "cols": len(dist), "data": dist},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": _flat(calib.arr(r))},
            "projection_matrix": {"rows": 3, "cols": 4, "data": _flat(calib.arr(p))},
        }
        text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=200)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(path)


def _flat(a: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(a, np.float64).ravel()]


def load_calibration(path: str | Path, image_size: tuple[int, int] | None = None
                     ) -> StereoCalibration:
    """Read a stereo calibration in any format this module understands.

    `path` is one file, `LEFT,RIGHT` (a ROS camera_info pair, or OpenCV's intrinsics and
    extrinsics files), or a folder holding them. `image_size` (w, h) is needed only for
    files that do not say it (OpenCV FileStorage output). ConfigError names the file, the
    missing or bad field and the formats understood.
    """
    return read_calibration(str(path), image_size)
