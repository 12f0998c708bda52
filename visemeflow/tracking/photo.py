"""L_rgb for the solvers: mouth-crop targets, per-vertex albedo estimated per utterance, rendering per frame."""

import numpy as np
import torch

from visemeflow.rig import VisemeRig, evaluate_rig
from visemeflow.render.camera import Intrinsics
from visemeflow.tracking.diffrender import (
    CropRasterizer,
    Light,
    crop_image,
    estimate_albedo,
    mouth_crop,
    project_to_crop,
    render_crop,
    rgb_loss,
    triangles_in_crop,
    visible_vertices,
)

ALBEDO_FRAMES = 12


class PhotoTerm:
    """Eq. 3 on a square mouth crop (`size` px) of every frame.

    `prepare` (called by the solver once a pose estimate exists) picks the triangles the crop can see and estimates
    the per-vertex albedo from up to 12 frames; `loss(j, vertices, rotation, translation)` renders frame j's crop
    and compares it with the video. Visibility is rasterised again every `refresh` calls per frame, the
    barycentrics (and so the gradients) every call.
    """

    def __init__(self, rig: VisemeRig, camera: Intrinsics, frames: np.ndarray, landmarks: np.ndarray,
                 size: int = 64, refresh: int = 5):
        self.rig, self.camera, self.refresh = rig, camera, refresh
        height, width = frames.shape[1:3]
        self.crop = mouth_crop(landmarks, size=size, image_size=(width, height))
        self.frames = frames
        self.targets = torch.stack([crop_image(f, self.crop) for f in frames])
        self.light = Light()
        self.rasterizer: CropRasterizer | None = None
        self.albedo: torch.Tensor | None = None
        self._fragments: dict[int, tuple[int, object]] = {}
        self.vertex_ids = np.zeros(0, np.int64)

    def prepare(self, curves: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> None:
        """Triangles in the crop and albedo from the current estimate (curves (T, 16), pose (T, 3) + (T, 3))."""
        with torch.no_grad():
            meshes = evaluate_rig(self.rig, torch.as_tensor(curves, dtype=torch.float32))
            grid = [project_to_crop(meshes[j], rotation[j], translation[j], self.camera, self.crop) for j in range(len(meshes))]
        pix = torch.stack([g[0] for g in grid]).numpy()
        faces = triangles_in_crop(self.rig.faces, pix, self.crop)
        self.rasterizer = CropRasterizer(self.rig.faces[faces], self.crop)
        ids = self.rasterizer.vertex_ids
        self.vertex_ids = np.asarray(ids)
        picks = np.unique(np.linspace(0, len(meshes) - 1, min(ALBEDO_FRAMES, len(meshes))).round().astype(int))
        images, pixels, seen = [], [], []
        for j in picks:
            p, d = grid[j][0][ids], grid[j][1][ids]
            fragments = self.rasterizer.rasterize(p, d)
            images.append(self.targets[j].numpy())
            pixels.append(p.numpy())
            seen.append(visible_vertices(fragments, p, d))
        self.albedo = torch.as_tensor(estimate_albedo(images, pixels, seen), dtype=torch.float32)
        self._fragments.clear()

    def loss(self, j: int, vertices: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
        """Eq. 3 for frame j; `vertices` (R, 3) are the rows `vertex_ids` of the posed rig's mesh."""
        if self.rasterizer is None or self.albedo is None:
            raise RuntimeError("PhotoTerm.prepare must run before loss")
        count, fragments = self._fragments.get(j, (0, None))
        if fragments is None or count % self.refresh == 0:
            fragments = None
        image, mask, fragments = render_crop(
            vertices, rotation, translation, self.camera, self.crop, None, self.albedo,
            self.light, rasterizer=self.rasterizer, return_fragments=True, fragments=fragments,
        )
        self._fragments[j] = (count + 1, fragments)
        return rgb_loss(image, self.targets[j], mask)
