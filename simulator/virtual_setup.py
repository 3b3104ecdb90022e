"""The paper's scan simulator (section III): a virtual light source and camera swept over a part.

The light source fires a fan of rays in its light plane; each ray's first hit on the CAD
model is a candidate point, kept when the camera sees it (the visibility check). The setup,
not the mesh, moves: at step ``n`` the light source and the camera stand at their step-0
positions plus ``n * step_mm`` along the motion axis (the paper's Eq. 4, with the depth-buffer
line's rays). Eq. 4's step number is any integer: the sweep covers every step whose light
plane meets the part, negative ones included, wherever the user puts the setup at step 0.
The only inputs are the two positions and the two densities (step size and rays per line).

Frames: everything is given and returned in one *setup frame* in which the part is fixed,
{T} in the CLI (the gripper frame: the part hangs along +z_T, the setup moves along +y_T
relative to it). The part's pose ^T X_P places the mesh in it; the rays are cast in the
part's own frame, so one Embree scene per part serves every grasp and misplacement.

A point is kept when the light source lights it (first hit), the camera stands on the lit
side of its surface (no point from the back side) and nothing on the mesh lies between the
camera and the point (Embree's occlusion query). The camera's field of view and the stripe's
image are not modelled here: `simulator.render` does that for whole frames.

While it sweeps, a cloud keeps only each point's ray and face (8 bytes a point, see
`simulator._sweep`); its float64 arrays are computed on first use, and its PLY file is
written straight from the rays and faces, so writing millions of points costs one pass.

The parts: the setup (``simulator.sweep_setup``), the sweep checked and laid out
(``simulator.sweep_plan``), the rays cast (``simulator.sweep_cast``), the cloud and its PLY
file (``simulator.sweep_cloud``). This module gathers their public names.
"""
from __future__ import annotations

from simulator.sweep_cast import predict_cloud, prepare, warm_up
from simulator.sweep_cloud import PredictedCloud, save_predicted_cloud
from simulator.sweep_plan import MAX_RAYS, SweepPlan, plan_sweep
from simulator.sweep_setup import (DEFAULT_RAYS_PER_LINE, DEFAULT_STEP_MM, MAIN_VIEW,
                                   SetupError, VirtualSetup, reference_setup)

__all__ = ["SetupError", "VirtualSetup", "PredictedCloud", "SweepPlan", "predict_cloud",
           "plan_sweep", "reference_setup", "save_predicted_cloud", "prepare", "warm_up",
           "DEFAULT_STEP_MM", "DEFAULT_RAYS_PER_LINE", "MAX_RAYS", "MAIN_VIEW"]
