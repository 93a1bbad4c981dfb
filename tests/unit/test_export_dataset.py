"""`trapflow dataset synth`: loaded the way Ultralytics and COCO tools load a dataset.

Ultralytics' path logic is re-implemented here as its loader has it: data.yaml's folder as
the root when there is no `path`, `train`/`val` folders of images, and each image's label
file found by putting labels/ for the last images/ in its path and .txt for its suffix.
The COCO file is read by pycocotools; its boxes must be the YOLO labels, back in pixels.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import pytest
import yaml
from click.testing import CliRunner

from trapflow.cli.dataset import dataset

IMG_FORMATS = {"bmp", "dng", "jpeg", "jpg", "mpo", "png", "tif", "tiff", "webp", "pfm"}
W, H = 320, 192


def img2label_path(img: str) -> str:
    """Ultralytics: /images/ -> /labels/ (the last one), suffix -> .txt."""
    sa, sb = f"{os.sep}images{os.sep}", f"{os.sep}labels{os.sep}"
    return sb.join(img.rsplit(sa, 1)).rsplit(".", 1)[0] + ".txt"


@pytest.fixture(scope="module")
def synth(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ds") / "crabs"
    res = CliRunner().invoke(dataset, ["synth", str(out), "--frames", "12", "--seed", "1",
                                       "--moving", "--width", str(W), "--height", str(H),
                                       "-o", "tags=1"])
    assert res.exit_code == 0, res.output
    return out


def load_ultralytics(data_file: Path, split: str) -> list[tuple[Path, list[list[float]]]]:
    data = yaml.safe_load(data_file.read_text())
    assert set(data) >= {"train", "val", "names"}
    root = Path(data.get("path") or data_file.parent)
    folder = root / data[split]
    images = sorted(p for p in folder.rglob("*") if p.suffix[1:].lower() in IMG_FORMATS)
    out = []
    for img in images:
        label = Path(img2label_path(str(img)))
        rows = [[float(v) for v in line.split()] for line in label.read_text().splitlines()
                if line.strip()] if label.exists() else []
        out.append((img, rows))
    return out


def test_ultralytics_finds_every_image_and_its_labels(synth: Path) -> None:
    data = yaml.safe_load((synth / "data.yaml").read_text())
    names = data["names"]
    assert names == {0: "crab", 1: "scallop", 2: "tag"}
    for split in ("train", "val"):
        items = load_ultralytics(synth / "data.yaml", split)
        assert len(items) == 12
        boxes = 0
        for img, rows in items:
            im = cv2.imread(str(img))
            assert im is not None and im.shape[:2] == (H, W)
            for row in rows:
                assert len(row) == 5 and int(row[0]) in names
                assert all(0.0 <= v <= 1.0 for v in row[1:])
                boxes += 1
        assert boxes > 0


def test_coco_json_loads_in_pycocotools_with_the_yolo_boxes(synth: Path) -> None:
    coco_mod = pytest.importorskip("pycocotools.coco", reason="pycocotools is not installed")
    coco = coco_mod.COCO(str(synth / "coco.json"))
    cats = {c["id"]: c["name"] for c in coco.loadCats(coco.getCatIds())}
    assert sorted(cats.values()) == ["crab", "scallop", "tag"]
    yolo = {img.stem: rows for img, rows in load_ultralytics(synth / "data.yaml", "train")}
    names = yaml.safe_load((synth / "data.yaml").read_text())["names"]
    assert len(coco.getImgIds()) == 12
    for image in coco.loadImgs(coco.getImgIds()):
        assert (synth / image["file_name"]).is_file()
        assert (image["width"], image["height"]) == (W, H)
        anns = coco.loadAnns(coco.getAnnIds(imgIds=[image["id"]]))
        rows = yolo[Path(image["file_name"]).stem]
        assert len(anns) == len(rows)
        for ann, (cls, cx, cy, bw, bh) in zip(anns, rows, strict=True):
            assert cats[ann["category_id"]] == names[int(cls)]
            x, y, w, h = ann["bbox"]
            assert x + w / 2 == pytest.approx(cx * W, abs=0.01)
            assert y + h / 2 == pytest.approx(cy * H, abs=0.01)
            assert (w, h) == (pytest.approx(bw * W, abs=0.01), pytest.approx(bh * H, abs=0.01))
            assert ann["area"] == pytest.approx(w * h, rel=1e-3) and ann["iscrowd"] == 0
