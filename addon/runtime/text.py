"""Text that fits: labels wrapped to the width of the region they are drawn in.

Blender's labels do not wrap; a long one is cut with an ellipsis in the middle ("Exact field
colo…andard', dither 0"). These helpers measure with the interface font (``blf``) and split text into
as many labels as it needs.
"""
from __future__ import annotations

import os

import bpy


def wrap_text(text: str, max_width: float, measure) -> list[str]:
    """Greedy word wrap of ``text`` into lines whose ``measure(line)`` (pixels) is <= ``max_width``.
    A word wider than a line (a long path) is split after '/' or, failing that, between characters."""
    lines: list[str] = []
    for para in str(text).split("\n"):
        line = ""
        for word in para.split(" "):
            cand = word if not line else line + " " + word
            if measure(cand) <= max_width:
                line = cand
                continue
            if line:
                lines.append(line)
                line = ""
            while measure(word) > max_width and len(word) > 1:  # split a long word
                cut = len(word) - 1
                while cut > 1 and measure(word[:cut]) > max_width:
                    cut -= 1
                slash = word.rfind("/", 1, cut)
                cut = slash + 1 if slash > 0 else cut
                lines.append(word[:cut])
                word = word[cut:]
            line = word
        lines.append(line)
    return lines


def file_size(path_or_bytes) -> str:
    """The size of a file (a path) or of a byte count, as people read it: '87 MB', '640 KB'."""
    n = os.path.getsize(path_or_bytes) if isinstance(path_or_bytes, str) else int(path_or_bytes)
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("KB", 1e3)):
        if n >= size:
            v = n / size
            return f"{v:.1f} {unit}" if v < 10 else f"{v:.0f} {unit}"
    return f"{n} bytes"


def ui_scale(context=None) -> float:
    try:
        scale = float((context or bpy.context).preferences.system.ui_scale)
    except Exception:  # noqa: BLE001
        scale = 0.0
    return scale if scale > 0 else 1.0  # 0 in background mode (no window)


def text_measure(context=None):
    """``measure(text) -> pixels`` in the interface font, as the UI draws labels."""
    scale = ui_scale(context)
    try:
        points = float((context or bpy.context).preferences.ui_styles[0].widget.points)
    except Exception:  # noqa: BLE001
        points = 11.0
    try:
        import blf

        # before 4.0 the size is in points at a dpi: the interface's own (int() of 72 x 1.0417 is 74,
        # which measures text 5 % shorter than it is drawn)
        try:
            dpi = int((context or bpy.context).preferences.system.dpi) or round(72 * scale)
        except Exception:  # noqa: BLE001
            dpi = round(72 * scale)

        def measure(s, _px=points * scale):
            if bpy.app.version >= (4, 0, 0):
                blf.size(0, _px)
            else:
                blf.size(0, points, dpi)
            return blf.dimensions(0, s)[0]

        if measure("abc xyz") > 0:
            return measure
    except Exception:  # noqa: BLE001
        pass
    # no fonts (Blender in background mode measures every text as 0 wide): a fair average width
    return lambda s: len(s) * 0.6 * points * scale


# What a panel leaves of its region's width to a label's text (pixels at interface scale 1), measured in
# Debian's Blender 3.4 in a real window (a sidebar 229 px wide shows 171 px of text, one with an icon
# 146 px; the Properties editor's 192 px region 157 px): the panel's margins, the tab strip of a
# sidebar with tabs, and an icon with its gap.
PANEL_MARGIN = 36
TAB_STRIP = 22
ICON_WIDTH = 24
TABBED = ("VIEW_3D", "IMAGE_EDITOR", "NODE_EDITOR", "SEQUENCE_EDITOR", "CLIP_EDITOR")


def text_width(context) -> float:
    """Pixels available for a label's text in the current region: its width less the panel's margins
    and, in a sidebar with tabs, the tab strip (no region, as in background mode: a 300 px sidebar)."""
    region = getattr(context, "region", None)
    if region is None or region.width <= 1:
        width, tabs = 300, True
    else:
        area = getattr(context, "area", None)
        width = region.width
        tabs = region.type == "UI" and getattr(area, "type", "") in TABBED
    return max(40.0, width - (PANEL_MARGIN + (TAB_STRIP if tabs else 0)) * ui_scale(context))


def wrapped_label(layout, text: str, width: float, icon: str = "NONE", context=None):
    """``text`` as as many labels as it needs to fit ``width`` pixels (:func:`text_width`); with an icon
    every line is indented by it (the icon on the first line, a blank one on the others)."""
    col = layout.column(align=True)
    if icon != "NONE":
        width = max(40.0, width - ICON_WIDTH * ui_scale(context))
    lines = wrap_text(text, width, text_measure(context)) or [""]
    for i, line in enumerate(lines):
        col.label(text=line, icon=icon if i == 0 else "BLANK1" if icon != "NONE" else "NONE")
    return col


def job_status(layout, job, context, cancel: str | None = None):
    """A background job in a panel: its ``status_lines()`` wrapped (the state's icon on the first), and
    while it runs a progress bar with the percentage and the ``cancel`` operator."""
    width = text_width(context)
    icon = "SORTTIME" if job.running else {"DONE": "CHECKMARK", "ERROR": "ERROR"}.get(job.state, "INFO")
    for i, line in enumerate(job.status_lines()):
        wrapped_label(layout, line, width, icon=icon if i == 0 else "NONE", context=context)
    if job.running:
        if hasattr(layout, "progress"):
            layout.progress(factor=job.fraction, text=f"{100 * job.fraction:.0f}%")
        if cancel:
            layout.operator(cancel, icon="CANCEL")


def labelled(layout, data, prop, label, **kw):
    """A property with its label above it (the sidebar is too narrow for both on one row)."""
    col = layout.column(align=True)
    col.label(text=label)
    col.prop(data, prop, text="", **kw)
    return col


def labelled_search(layout, data, prop, search_data, search_prop, label, **kw):
    """``prop_search`` with its label above it (vertex groups, UV maps: names need the full width)."""
    col = layout.column(align=True)
    col.label(text=label)
    col.prop_search(data, prop, search_data, search_prop, text="", **kw)
    return col
