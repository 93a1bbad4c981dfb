"""Thumbnails over the modem: fitted to the byte budget, decoded from the packets alone
(the header left out), and a lost packet costs only its rows."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from trapflow.modem import thumb


def _crop(w: int = 200, h: int = 120) -> np.ndarray:
    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur(rng.integers(0, 255, (h, w, 3), dtype=np.uint8), (0, 0), 3)
    cv2.circle(img, (w // 2, h // 2), h // 4, (0, 0, 255), -1)
    return img


@pytest.mark.parametrize("budget", [128, 256, 512])
@pytest.mark.parametrize("colour", [True, False])
def test_fits_the_budget_and_decodes_without_the_header(budget: int, colour: bool) -> None:
    crop = _crop()
    packets = thumb.fit(crop, budget, colour)
    assert packets and sum(p.cost() for p in packets) <= budget
    assert all(len(p.data) <= thumb.MAX_PACKET for p in packets)
    assert not any(b"\xff\xd8" in p.data or b"\xff\xdb" in p.data for p in packets)
    img = thumb.decode(packets)
    p0 = packets[0]
    assert img.shape[:2] == (p0.height, p0.width)
    ref = cv2.resize(crop if colour else cv2.cvtColor(crop, cv2.COLOR_BGR2GRAY),
                     (p0.width, p0.height), interpolation=cv2.INTER_AREA)
    assert np.abs(img.astype(int) - ref.astype(int)).mean() < 20


def test_larger_budgets_give_larger_or_better_thumbnails() -> None:
    got = [thumb.fit(_crop(), b)[0] for b in (128, 256, 512)]
    assert [p.width * p.height * p.quality for p in got] == sorted(
        p.width * p.height * p.quality for p in got)


def test_a_lost_packet_costs_its_rows_only() -> None:
    packets = thumb.fit(_crop(), 512)
    assert len(packets) >= 3
    whole = thumb.decode(packets).astype(int)
    for lost in range(len(packets)):
        part = thumb.decode(packets[:lost] + packets[lost + 1:]).astype(int)
        rows = np.abs(part - whole).reshape(whole.shape[0], -1).max(axis=1) > 0
        # only the lost packet's rows (MCU rows of 16 px) differ
        assert 0 < rows.sum() < whole.shape[0]
        # any order, any subset of the rest decodes the same
        assert (thumb.decode(list(reversed(packets[:lost] + packets[lost + 1:])))
                .astype(int) == part).all()


def test_header_is_the_one_the_encoder_writes() -> None:
    img = cv2.resize(_crop(), (64, 40))
    ok, buf = cv2.imencode(".jpg", img, thumb._params(40, 4))
    assert ok and buf.tobytes().startswith(thumb.header(64, 40, 40, True, 4))


def test_nothing_fits_a_tiny_budget() -> None:
    assert thumb.fit(_crop(), 10) == []
    with pytest.raises(ValueError):
        thumb.assemble([])
