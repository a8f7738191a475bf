"""The built-in scene's texture: a high-frequency solid texture (stripes/checker + stroke lettering)."""
from __future__ import annotations

import math

import numpy as np
import torch

from .shape import surface_normal

_FONT = {  # 5x7 bitmap glyphs
    "N": ["X...X", "XX..X", "X.X.X", "X..XX", "X...X", "X...X", "X...X"],
    "E": ["XXXXX", "X....", "X....", "XXXX.", "X....", "X....", "XXXXX"],
    "U": ["X...X", "X...X", "X...X", "X...X", "X...X", "X...X", ".XXX."],
    "M": ["X...X", "XX.XX", "X.X.X", "X.X.X", "X...X", "X...X", "X...X"],
    "S": [".XXXX", "X....", "X....", ".XXX.", "....X", "....X", "XXXX."],
    "H": ["X...X", "X...X", "X...X", "XXXXX", "X...X", "X...X", "X...X"],
    "R": ["XXXX.", "X...X", "X...X", "XXXX.", "X.X..", "X..X.", "X...X"],
    "F": ["XXXXX", "X....", "X....", "XXXX.", "X....", "X....", "X...."],
    "7": ["XXXXX", "....X", "...X.", "..X..", ".X...", ".X...", ".X..."],
    "Z": ["XXXXX", "....X", "...X.", "..X..", ".X...", "X....", "XXXXX"],
    " ": ["....."] * 7,
}
_TEXT_ROWS = ["NEUMESH NERF 7 ", "SHUZ MESH FUNE "]  # two lines of "lettering" around the equator
_GLYPHS_AROUND = 22
_PALETTE = np.array(
    [[0.85, 0.12, 0.10], [0.98, 0.80, 0.10], [0.10, 0.35, 0.85], [0.10, 0.65, 0.25],
     [0.95, 0.50, 0.05], [0.55, 0.15, 0.65]],
    dtype=np.float32,
)
_PAPER = np.array([0.95, 0.93, 0.85], dtype=np.float32)
_INK = np.array([0.05, 0.05, 0.12], dtype=np.float32)


def _font_bits(text: str) -> np.ndarray:
    return np.array([[[ch == "X" for ch in row] for row in _FONT[c]] for c in text], dtype=bool)


def _bit_lookup(bits: torch.Tensor, glyph: torch.Tensor, bx: torch.Tensor, by: torch.Tensor) -> torch.Tensor:
    inside = (bx >= 0) & (bx < 5) & (by >= 0) & (by < 7)
    val = bits[glyph, by.clamp(0, 6), bx.clamp(0, 4)]
    return val & inside


def default_texture(points, normals=None):
    """Albedo (N,3) in [0,1] of the solid texture at 3D surface points (N,3).

    Latitude stripes in six saturated colours times a longitude checker; two rows of stroke lettering
    (dark ink on paper) in a band around the equator; near the poles a fine triplanar checker whose
    projection axis follows ``normals`` (the analytic normal is used when ``normals`` is None).
    Numpy in -> numpy float32 out; torch in -> torch out.
    """
    is_np = not isinstance(points, torch.Tensor)
    p = torch.as_tensor(np.asarray(points, dtype=np.float32) if is_np else points).to(torch.float32)
    if normals is None:
        n = surface_normal(p.double()).float()
    else:
        n = torch.as_tensor(np.asarray(normals, dtype=np.float32) if is_np else normals).to(torch.float32)
    u = p / p.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    theta = torch.acos(u[:, 2].clamp(-1, 1))  # 0 at +z pole
    phi = torch.atan2(u[:, 1], u[:, 0]) + math.pi  # [0, 2pi]
    pal = torch.as_tensor(_PALETTE)
    # stripes x checker
    band = torch.floor(theta / (math.pi / 14)).long()
    sector = torch.floor(phi / (2 * math.pi / 20)).long()
    col = pal[band % len(_PALETTE)]
    dark = ((band + sector) % 2 == 1).float()[:, None]
    col = col * (1.0 - 0.45 * dark) + 0.08 * dark
    # lettering band: theta in [pi/2 - 0.36, pi/2 + 0.36] holds two text rows
    cell_w = 2 * math.pi / _GLYPHS_AROUND
    cell_h = cell_w * 1.25
    row_f = (theta - (math.pi / 2 - cell_h)) / cell_h
    row = torch.floor(row_f).long()
    in_band = (row >= 0) & (row < 2)
    gx = phi / cell_w
    gcol = torch.floor(gx).long() % _GLYPHS_AROUND
    lx = (gx - torch.floor(gx)) * 6.0 - 0.5  # 5 bit columns + spacing
    ly = (row_f - torch.floor(row_f)) * 8.5 - 0.75  # 7 bit rows + spacing
    bx = torch.floor(lx).long()
    by = torch.floor(ly).long()
    fx, fy = lx - bx, ly - by
    ink = torch.zeros_like(theta, dtype=torch.bool)
    half = 0.24  # stroke half width in bit units (thin strokes)
    for r_i, text in enumerate(_TEXT_ROWS):
        bits = torch.as_tensor(_font_bits(text))
        glyph = (gcol + 3 * r_i) % len(text)
        sel = in_band & (row == r_i)
        node = _bit_lookup(bits, glyph, bx, by)
        right = _bit_lookup(bits, glyph, bx + 1, by)
        left = _bit_lookup(bits, glyph, bx - 1, by)
        down = _bit_lookup(bits, glyph, bx, by + 1)
        up = _bit_lookup(bits, glyph, bx, by - 1)
        cx_ok = (fx - 0.5).abs() < half
        cy_ok = (fy - 0.5).abs() < half
        stroke = node & cx_ok & cy_ok
        stroke |= node & cy_ok & ((right & (fx >= 0.5)) | (left & (fx <= 0.5)))
        stroke |= node & cx_ok & ((down & (fy >= 0.5)) | (up & (fy <= 0.5)))
        ink |= sel & stroke
    paper = torch.as_tensor(_PAPER).expand_as(col)
    col = torch.where(in_band[:, None], paper, col)
    col = torch.where(ink[:, None], torch.as_tensor(_INK).expand_as(col), col)
    # poles: triplanar fine checker (projection axis = dominant normal axis)
    polar = u[:, 2].abs() > 0.93
    axis = n.abs().argmax(-1)
    q = torch.floor(p * 12.0).long()
    c0 = torch.where(axis == 0, q[:, 1] + q[:, 2], torch.where(axis == 1, q[:, 0] + q[:, 2], q[:, 0] + q[:, 1]))
    pole_col = torch.where((c0 % 2 == 0)[:, None], pal[2].expand_as(col), pal[1].expand_as(col))
    col = torch.where(polar[:, None], pole_col, col)
    col = col.clamp(0.0, 1.0)
    return col.numpy().astype(np.float32) if is_np else col


# --------------------------------------------------------------------------------------------
# ground-truth ray tracer
# --------------------------------------------------------------------------------------------
