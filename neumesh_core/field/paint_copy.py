"""The premultiplied copy of a paint atlas's image (field/paint_atlas.py): what a render samples,
kept in step with the image while a paint program writes texels in one thread and a render samples
in another.

The copy is built from the whole image (seconds at 4096^2 on a busy CPU) without holding the lock
that writers take, so that a stroke never waits for it; texels written during a build are listed and
taken from the image again once it is done.  Without that list a texel written mid-build would keep
the colour read before the write and the alpha read after it: black paint where the stroke is.
"""
from __future__ import annotations

import threading

import numpy as np


def premultiply(rows: np.ndarray) -> np.ndarray:
    """(..., 4) straight-alpha RGBA -> premultiplied float16 RGBA."""
    return np.concatenate([rows[..., :3] * rows[..., 3:], rows[..., 3:]], -1).astype(np.float16)


class PremultipliedCopy:
    """(copy (H,W,4) float16, any paint) of an (H,W,4) float32 image, updated texel by texel."""

    def __init__(self):
        self._state = None                  # (copy, any paint) or None: built on the next read
        self._lock = threading.Lock()       # guards _state, _pending, _generation
        self._build_lock = threading.Lock() # one build at a time
        self._pending = None                # texel arrays written during a build (None: no build)
        self._generation = 0                # bumped when the whole image changed

    def __deepcopy__(self, memo):
        return PremultipliedCopy()          # a copied atlas builds its own from its copied image

    def invalidate(self) -> None:
        """The whole image changed: built again on the next read."""
        with self._lock:
            self._state = None
            self._generation += 1

    def update(self, image: np.ndarray, texels: np.ndarray) -> None:
        """``texels`` (flat indices) of ``image`` were written: take them again (after the build when
        one is running)."""
        t = np.asarray(texels, np.int64).reshape(-1)
        if len(t) == 0:
            return
        with self._lock:
            if self._state is None:
                if self._pending is not None:
                    self._pending.append(t)
                return
            self._state = self._updated(self._state, image, t)

    @staticmethod
    def _updated(state: tuple, image: np.ndarray, t: np.ndarray) -> tuple:
        rows = image.reshape(-1, 4)[t]
        pm = state[0].reshape(-1, 4)
        pm[t] = premultiply(rows)
        any_paint = state[1] or bool((rows[:, 3] > 0).any())
        if state[1] and not (rows[:, 3] > 0).all():
            any_paint = bool((pm[:, 3] > 0).any())        # paint taken away (undo): look again
        return state[0], any_paint

    def get(self, image: np.ndarray) -> tuple:
        """(copy, any paint) of ``image``, built when there is none."""
        state = self._state
        if state is not None:
            return state
        with self._build_lock:
            with self._lock:
                if self._state is not None:
                    return self._state
                self._pending, generation = [], self._generation
            state = (premultiply(image), bool((image[..., 3] > 0).any()))   # writers go on meanwhile
            with self._lock:
                pending, self._pending = self._pending, None
                if pending:
                    state = self._updated(state, image, np.unique(np.concatenate(pending)))
                if generation == self._generation:   # else the whole image changed: built again next time
                    self._state = state
                return state
