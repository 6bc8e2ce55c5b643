"""A small caption in a frame's top-left corner (task, ψ, time, keyframes hit, the acting policy).

Drawn with Pillow in DejaVu Sans (matplotlib ships it) so ψ and φ print; OpenCV's fonts are ASCII only.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np


@lru_cache(maxsize=8)
def _font(size: int):
    from matplotlib import font_manager
    from PIL import ImageFont

    return ImageFont.truetype(font_manager.findfont("DejaVu Sans"), size)


def draw_caption(frame: np.ndarray, lines: list[str], scale: float = 1.0) -> np.ndarray:
    """The frame (H, W, 3 uint8) with `lines` on a dark translucent box; returns a new array. Only the box's
    corner of the frame is composited (a whole 1280x720 frame through Pillow costs more than the text)."""
    if not lines:
        return frame
    from PIL import Image, ImageDraw

    size = max(10, int(round(frame.shape[0] / 36 * scale)))
    font = _font(size)
    pad, gap = size // 2, size // 4
    widths = [font.getlength(line) for line in lines]
    box_w = int(max(widths)) + 2 * pad
    box_h = len(lines) * size + (len(lines) - 1) * gap + 2 * pad
    corner_h, corner_w = min(frame.shape[0], box_h + 2 * pad), min(frame.shape[1], box_w + 2 * pad)
    out = np.array(frame[..., :3], copy=True)
    corner = Image.fromarray(np.ascontiguousarray(out[:corner_h, :corner_w])).convert("RGBA")
    overlay = Image.new("RGBA", corner.size, (0, 0, 0, 0))
    draw = ImageDraw.Draw(overlay)
    draw.rectangle([pad, pad, pad + box_w, pad + box_h], fill=(0, 0, 0, 140))
    for i, line in enumerate(lines):
        draw.text((2 * pad, 2 * pad + i * (size + gap)), line, font=font, fill=(255, 255, 255, 255))
    out[:corner_h, :corner_w] = np.asarray(Image.alpha_composite(corner, overlay).convert("RGB"))
    return out
