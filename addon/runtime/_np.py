"""numpy, imported on first use.

Some Blender builds (e.g. Debian's) ship without numpy; the add-on must still register and show its
preferences there, so no module imports numpy at import time.
"""


class _LazyNumpy:
    _mod = None

    def __getattr__(self, name):
        mod = _LazyNumpy._mod
        if mod is None:
            import numpy as mod  # noqa: PLC0415

            _LazyNumpy._mod = mod
        return getattr(mod, name)


np = _LazyNumpy()
