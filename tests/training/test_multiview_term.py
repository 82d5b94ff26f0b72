"""--surface-multiview: PGSR's multi-view geometric consistency, a pixel's round trip to a neighbouring view and back
by the two depth maps (geometry/reprojection.py), and the loss term that holds it small (surface_terms.MultiView)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from mcsplat.camera import Camera, intrinsics
from mcsplat.gaussians import GaussianModel
from mcsplat.geometry.reprojection import neighbours, round_trip_error
from mcsplat.render import render
from mcsplat.surface_terms import MultiView, surface_terms

from tests.render.test_normals import flat_disk
from tests.training.test_surface_terms import context, flat_model

F64 = torch.float64


def looking_at_origin(angle_degrees: float, distance: float = 3.0, width: int = 48, height: int = 40) -> Camera:
    """A camera on a circle about the y axis, `angle_degrees` round from the -z axis, looking at the origin."""
    angle = math.radians(angle_degrees)
    rotation = torch.tensor([[math.cos(angle), 0.0, -math.sin(angle)], [0.0, 1.0, 0.0],
                             [math.sin(angle), 0.0, math.cos(angle)]], dtype=F64)
    w2c = torch.eye(4, dtype=F64)
    w2c[:3, :3] = rotation
    w2c[2, 3] = distance
    return Camera(K=intrinsics(40.0, 40.0, width / 2, height / 2).double(), world_to_camera=w2c, width=width,
                  height=height)


def plane_depth(camera: Camera, normal: torch.Tensor, offset: float) -> torch.Tensor:
    """[H, W] camera depth of the plane normal . x = offset along each pixel's ray (0 where it does not meet it
    in front)."""
    K, w2c = camera.K, camera.world_to_camera
    u = torch.arange(camera.width, dtype=F64) + 0.5
    v = torch.arange(camera.height, dtype=F64) + 0.5
    rays = torch.stack([((u[None, :] - K[0, 2]) / K[0, 0]).expand(camera.height, -1),
                        ((v[:, None] - K[1, 2]) / K[1, 1]).expand(-1, camera.width),
                        torch.ones(camera.height, camera.width, dtype=F64)], dim=-1)  # camera z = 1
    centre = -w2c[:3, :3].T @ w2c[:3, 3]
    along = (rays @ w2c[:3, :3]) @ normal  # the world direction of each ray, against the normal
    depth = (offset - normal @ centre) / along
    return torch.where(depth > 0, depth, torch.zeros_like(depth))


def test_a_pixel_of_a_plane_comes_back_where_it_started_and_a_wrong_depth_does_not():
    normal = torch.tensor([0.0, math.sin(0.3), math.cos(0.3)], dtype=F64)
    one, other = looking_at_origin(0.0), looking_at_origin(12.0)
    depth, other_depth = plane_depth(one, normal, 0.2), plane_depth(other, normal, 0.2)
    error, valid = round_trip_error(depth, one, other_depth, other)
    assert valid.float().mean() > 0.6 and error[valid].max() < 1e-5  # exact, but for the square root's 1e-6
    farther = (depth * 1.1).requires_grad_()
    error, valid = round_trip_error(farther, one, other_depth, other)
    assert error[valid].median() > 0.5
    error.sum().backward()
    pulled_back = farther.grad[valid] > 0  # less depth, less error: the gradient points back toward the plane
    assert pulled_back.float().mean() > 0.95


def test_the_neighbours_are_the_nearest_views_looking_within_thirty_degrees():
    ring = [looking_at_origin(14.4 * k) for k in range(25)]  # 14.4 degrees apart, all looking in
    found = neighbours(ring, count=8)
    assert sorted(found[0][:2]) == [1, 24] and sorted(found[0]) == [1, 2, 23, 24]
    assert neighbours(ring, count=1)[5] in ([4], [6])


@dataclass
class Photo:
    """What the term reads of a training view."""
    camera: Camera

    def camera_at(self, scale: float) -> Camera:
        return self.camera


def test_the_multiview_term_is_zero_on_an_opaque_plane_and_positive_where_the_views_disagree():
    one, other = looking_at_origin(0.0, width=45, height=37), looking_at_origin(10.0, width=45, height=37)
    term = MultiView(1.0, start_share=0.0, views=[Photo(one), Photo(other)])
    disk = flat_disk(20.0, radius=1.0)
    seen = render(disk, one, outputs={"normals", "planar_depth"})
    target = torch.full((37, 45, 3), 0.5, dtype=F64)
    step = context(seen, disk, one, target)
    step = type(step)(**{**vars(step), "view": Photo(one)})
    assert term(step).item() < 1e-6
    layered = flat_model(60, seed=4, opacity=0.5)
    layered = GaussianModel(**{k: v.detach().double() for k, v in layered.params.items()})
    layered.params["means"].data *= 0.3
    seen = render(layered, one, outputs={"normals", "planar_depth"})
    step = type(step)(**{**vars(context(seen, layered, one, target)), "view": Photo(one)})
    value = term(step)
    assert value.item() > 1e-3
    value.backward()
    assert layered.params["means"].grad.abs().max() > 0


def test_surface_options_add_the_term_off_unless_weighted():
    terms = surface_terms(100.0, 0.015, 0.2, 1.0, 0.0, 0.0, [Photo(looking_at_origin(0.0))])
    multiview = terms[-1]
    assert isinstance(multiview, MultiView) and not multiview.active(99, 100) and multiview.neighbours == []
