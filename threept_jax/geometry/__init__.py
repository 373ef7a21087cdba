"""Geometry core: rotations, rotation grids, cameras, boxes, NMS, SO(3) KDE, PnP, triangulation.

Conventions (docs/design.md section 3): millimetres; OpenCV camera (x right, y down, z forward);
``T_cam_obj`` maps object points into the camera; rotations are 3x3 matrices at API
boundaries; every function is batched over leading axes and jit-able.
"""
