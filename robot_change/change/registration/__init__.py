"""Registration of the current view to the station's reference: where the camera stands now.

ALGORITHM.md section 4, as built (docs/algorithm.md, "Registration"): projective point-to-plane
ICP of the current depth image against the reference's fused depth image, as KinectFusion tracks
a camera (Newcombe et al. 2011), coarse to fine on depth pyramids, with

* **vertex maps by block averaging of 3-D points** (not of depths): a cell of a level is the
  mean of the back-projected readings of its ``f x f`` block that lie within a depth band about
  the mean reading of the block's central 2 x 2 pixels (a depth edge does not blend fore- and
  background).  Averaging over a
  block also smooths out the Kinect's disparity quantisation terraces, the trap of
  ALGORITHM.md section 4 (two clouds' terraces line up better than their surfaces);
* **normals** from central differences of the vertex map, refused across depth edges;
* **projective association**: a current cell, moved by the estimate, is projected into the
  reference level and paired with the cell it lands on, if the two are within a distance that
  shrinks level by level and their normals agree;
* **weights**: residuals are divided by the depth noise at the point (Kinect axial noise plus
  quantisation, both growing with z^2, so near surfaces count more), then a Tukey kernel with
  a scale from the median absolute residual: the change is what does not fit;
* **degeneracy**: the 6x6 normal matrix, rotations scaled by the cloud's radius to metres, is
  decomposed; directions with little information (a bare wall leaves translations along it
  free) are not moved along and are reported (Zhang, Kaess & Singh 2016), and so is a slide
  that no surface facing along it pins at the estimate;
* **searches**: offsets along the two least constrained directions, 10 cm apart, scored by
  inliers less the cells either view sees through; then, along a slide (one direction far
  less constrained than the others: a table before a wall), 1 cm apart;
* **table-plane starts** (a table top only: a dominant plane of at most 2 m): top-down
  occupancy grids of the two views on their planes, cross-correlated by FFT over in-plane
  shifts for a few yaws, give starts for (x, y, yaw) in the plane that ICP from the main
  estimate cannot reach when moved objects drag it; they compete with the main estimate on a
  score taken both ways (docs/algorithm.md, step 6b);
* **trimming the change** (a table top only): the objects (cells above the table) that
  contradict the other view more than they fit it are left out and ICP is run again on the
  table and the objects that stayed put, twice (docs/algorithm.md, step 6c);
* **fitness**: the fraction of current cells with an inlier correspondence at the end, and the
  RMSE of those.  Low fitness, or an offset beyond the station tolerance, is "not at the
  station", a different answer from "changed" (decided in :mod:`robot_change.change.detect`).

The floor stays in: registration runs on the depth images, before plane removal.

Numeric package: arrays in, arrays out.  Its modules, each with one job:

* :mod:`.params` -- RegistrationParams (every setting and its default);
* :mod:`.result` -- Registration (the estimate, fitness, weak directions, the station test);
* :mod:`.rigid` -- rigid transforms and rotation angles;
* :mod:`.pyramid` -- depth pyramids (vertex and normal maps) and the depth noise;
* :mod:`.icp` -- one level's ICP: association, weighted normal equations, Gauss-Newton;
* :mod:`.agreement` -- how well two views agree at a pose: scores, the weak-direction search,
  fitness, the seen-through share;
* :mod:`.table_top` -- the table-top gate, starts, trimming and weak-pose checks;
* :mod:`.register` -- :func:`register_depth`, the whole estimate coarse to fine.

Kernels are ``@njit(cache=True, nogil=True)`` with NumPy twins in
``tests/test_registration.py``.
"""

from __future__ import annotations

from .params import RegistrationParams
from .register import register_depth
from .result import AXES, Registration, identity_registration
from .rigid import (
    invert,
    rotation_angle_deg,
    rotation_to_rpy_deg,
    rpy_deg_to_rotation,
    transform_points,
)

__all__ = [
    "AXES",
    "Registration",
    "RegistrationParams",
    "identity_registration",
    "invert",
    "register_depth",
    "rotation_angle_deg",
    "rotation_to_rpy_deg",
    "rpy_deg_to_rotation",
    "transform_points",
]
