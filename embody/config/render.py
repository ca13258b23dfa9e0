"""`render`: offscreen MuJoCo rendering of reference and robot, keyframes, sheet and preview."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from embody.config.base import Section

View = Literal["front", "side"]


class RenderConfig(Section):
    #: Size of one sheet image (and of what `SceneRenderer` returns).
    width: int = Field(320, ge=16, le=4096)
    height: int = Field(240, ge=16, le=4096)
    #: Images are drawn at this multiple of width×height without multisampling and box-filtered
    #: down (antialiasing); the preview uses them as drawn (640×480 per body by default). On
    #: software GL the 4× multisample resolve costs more than the extra pixels.
    supersample: int = Field(2, ge=1, le=4)
    #: Keyframes per sequence, picked at motion extrema (holds and extreme wrist positions).
    keyframes: int = Field(8, ge=1, le=64)
    #: Cameras, each a row pair (reference over robot) in the comparison sheet. The side view
    #: shows depth errors (hands too far forward) that are invisible from the front.
    views: list[View] = ["front", "side"]
    #: OpenGL backend; osmesa needs `libosmesa6`. egl falls back to osmesa when it fails.
    gl: Literal["egl", "osmesa"] = "egl"
    #: Hide geometry below the torso (legs): signing is upper-body, and it halves render time.
    #: The reference body's legs (hips down) are left out with the robot's.
    upper_body: bool = True
    #: Robot meshes are decimated on a grid of this cell size (m) for rendering only; 0 keeps
    #: them whole. Software GL's cost follows the triangle count, hardly the pixels: 8 mm (about
    #: 1.5 px at 320×240 and 1.2 m) draws G1's upper body with 48k instead of 470k triangles.
    mesh_cell_m: float = Field(0.008, ge=0.0, le=0.05)
    #: The robot's meshes outside the hands (torso, head, arms: large and smooth) on a coarser
    #: grid; null: `mesh_cell_m`. 16 mm draws G1's upper body with 12k instead of 25k
    #: triangles; the hands (the wrist links and below) keep `mesh_cell_m`.
    robot_body_cell_m: float | None = Field(0.016, ge=0.0, le=0.05)
    #: The reference body's hands (wrist and finger bones) are decimated the same way (within
    #: each rigid piece and skinning bone, so fingers never merge). 0 keeps them whole.
    reference_cell_m: float = Field(0.006, ge=0.0, le=0.05)
    #: The rest of the reference body (large smooth segments) on a coarser grid; null: the
    #: hands' `reference_cell_m`. 20 mm draws the whole body with ~19k instead of ~43k
    #: triangles (each re-uploaded every frame); shading stays smooth (normals per frame).
    reference_body_cell_m: float | None = Field(0.02, ge=0.0, le=0.05)
    #: Free-camera look-at point in the robot torso frame (metres) and distance; null (default)
    #: frames both bodies automatically: head, T-pose arms and raised hands inside the frame,
    #: for any robot size (`embody.render.framing`). The same camera sees human and robot.
    lookat: tuple[float, float, float] | None = None
    camera_distance: float | None = Field(None, gt=0.1, le=20.0)
    camera_elevation: float = Field(-5.0, ge=-89.0, le=89.0)
    #: Colour of the reference body mesh (RGBA 0..1).
    reference_rgba: tuple[float, float, float, float] = (0.85, 0.62, 0.42, 1.0)
    #: The robot is drawn in one light material (its own dark materials vanish against a dark
    #: background at 320×240), on a neutral light background, so hands, fingers and face read.
    robot_rgba: tuple[float, float, float, float] = (0.93, 0.93, 0.91, 1.0)
    background_rgb: tuple[float, float, float] = (0.62, 0.66, 0.72)
    #: Animated preview: mp4 needs imageio-ffmpeg (falls back to gif), none disables it.
    preview_format: Literal["mp4", "gif", "webp", "none"] = "mp4"
    #: Preview frames per second of motion (plays in real time); null: the source frame rate.
    #: 15 (every 2nd frame of 30 fps sources) halves the preview's drawing and encoding.
    preview_fps: float | None = Field(15.0, gt=0.0, le=240.0)
    #: The preview shows only the part of the drawn frame that the bodies reach in the
    #: sequence (plus a few pixels), at the drawn scale: the framing leaves room for any pose
    #: (raised hands), which a sequence seldom uses, and drawing and encoding pay per pixel.
    preview_crop: bool = True
    #: Frames rendered for the preview at most (longer sequences are evenly subsampled, still
    #: playing in real time); at 30 fps the default covers a minute.
    preview_max_frames: int = Field(1800, ge=2, le=100_000)

    @field_validator("views")
    @classmethod
    def _unique_views(cls, views: list[str]) -> list[str]:
        if not views or len(set(views)) != len(views):
            raise ValueError("views must be a non-empty list without repeats")
        return views
