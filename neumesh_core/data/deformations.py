"""Deformations of rest vertices (numpy (N,3) -> (N,3)) used to measure deformation fidelity.

Each is a plain function of the rest positions, applied alike to the field (``field.set_vertices``)
and to the mesh the ground truth traces (:mod:`neumesh_core.data.mesh_truth`).  They act along the z
axis of the built-in scene's blob (extent about [-1.25, 1.3]); ``LENGTH`` is the length over which a
bend's or twist's angle is spread (Blender's Simple Deform spreads it over the object's extent).
"""
from __future__ import annotations

import math

import numpy as np

LENGTH = 2.5


def bend(v, degrees: float, length: float = LENGTH):
    """Bend the z axis into an arc in the x-z plane turning by ``degrees`` over ``length``."""
    v = np.asarray(v, np.float64)
    radius = length / math.radians(degrees)
    th = v[:, 2] / radius
    r = radius - v[:, 0]
    return np.stack([radius - r * np.cos(th), v[:, 1], r * np.sin(th)], 1)


def twist(v, degrees: float, length: float = LENGTH):
    """Rotate about the z axis by an angle proportional to z: ``degrees`` over ``length``."""
    v = np.asarray(v, np.float64)
    a = math.radians(degrees) * v[:, 2] / length
    c, s = np.cos(a), np.sin(a)
    return np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]], 1)


def stretch(v, factor: float):
    """Scale along z by ``factor`` (a stretch when > 1, a squash when < 1); x and y unchanged."""
    return np.asarray(v, np.float64) * np.array([1.0, 1.0, float(factor)])


def crease(v, degrees: float = 60.0, blend: float = 0.35):
    """Two-bone crease: the upper bone (z > 0) turns by ``degrees`` about the y axis through the
    joint at the origin; linear-blend skinning with weights rising smoothly (smoothstep) from 0 to
    1 over z in [-blend, blend] (what Blender's automatic weights give a two-bone chain)."""
    v = np.asarray(v, np.float64)
    s = np.clip((v[:, 2] + blend) / (2 * blend), 0.0, 1.0)
    w = s * s * (3 - 2 * s)
    a = math.radians(degrees)
    rot = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    return (1 - w)[:, None] * v + w[:, None] * (v @ rot.T)


# name -> function of the rest vertices; in increasing strength within each kind.  bend140 and
# crease60 turn part of the surface inside out (the Jacobian's determinant is negative on 3% and 6.5%
# of the triangles, see inverted_fraction): no physical surface does that, and a field's shell, which
# lies on the inner side of its surface, ends up outside there.  The others keep det J > 0.
DEFORMATIONS = {
    "bend35": lambda v: bend(v, 35),
    "bend70": lambda v: bend(v, 70),
    "bend140": lambda v: bend(v, 140),
    "twist90": lambda v: twist(v, 90),
    "stretch1p3": lambda v: stretch(v, 1.3),
    "stretch2": lambda v: stretch(v, 2.0),
    "squash0p7": lambda v: stretch(v, 0.7),
    "crease45": lambda v: crease(v, 45, blend=0.9),   # weights spread over most of the body
    "crease60": lambda v: crease(v, 60, blend=0.35),  # a narrow blend: turns 6.5% of it inside out
}


def inverted_fraction(fn, rest_vertices, faces, h: float = 1e-4) -> float:
    """Fraction of triangles at whose centroid the deformation ``fn`` reverses orientation
    (det of its Jacobian < 0, central differences): where it turns the surface inside out."""
    v = np.asarray(rest_vertices, np.float64)
    c = v[np.asarray(faces)].mean(1)
    eye = np.eye(3)
    J = np.stack([(fn(c + h * eye[i]) - fn(c - h * eye[i])) / (2 * h) for i in range(3)], -1)
    return float((np.linalg.det(J) < 0).mean())
