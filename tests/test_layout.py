"""Camera-layout figure (report.layout): frustum geometry and the SVG it writes."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dmais_pipe.camera import Camera
from dmais_pipe.errors import DmaisError
from dmais_pipe.geometry import Rigid3
from dmais_pipe.report.layout import artist_id, frustum_segments, write_layout_svg
from dmais_pipe.rig import Rig

SVG = "{http://www.w3.org/2000/svg}"


def _rig(tilt_deg: float = 45.0, shift: float = 0.0) -> Rig:
    """Three cameras: A at the origin looking along z, B and C tilted about x and y, 0.1 m away."""
    camera = Camera(2000.0, 2100.0, 511.5, 383.5, 0.0, 1024, 768)
    rig_from_cam = {
        "A": Rigid3.identity(),
        "B": Rigid3(Rotation.from_euler("x", tilt_deg, degrees=True).as_matrix(), [0.0, 0.1 + shift, 0.0]),
        "C": Rigid3(Rotation.from_euler("y", -tilt_deg, degrees=True).as_matrix(), [-0.1, 0.0, shift]),
    }
    return Rig({c: camera for c in rig_from_cam}, {c: T.inverse() for c, T in rig_from_cam.items()}, "A")


def test_frustum_has_apex_at_the_centre_and_far_corners_on_the_image_corners():
    rig = _rig()
    segments = frustum_segments(rig, "B", depth=0.3)
    assert segments.shape == (8, 2, 3)
    centre = rig.camera_center("B")
    np.testing.assert_allclose(segments[:4, 0], np.tile(centre, (4, 1)))
    far = segments[:4, 1]
    cam_from_rig = rig.cam_from_rig["B"]
    in_camera = cam_from_rig.apply(far)
    np.testing.assert_allclose(in_camera[:, 2], 0.3)  # depth along B's optical axis
    corners = rig.cameras["B"].project(in_camera)
    np.testing.assert_allclose(corners, [[-0.5, -0.5], [1023.5, -0.5], [1023.5, 767.5], [-0.5, 767.5]], atol=1e-9)
    np.testing.assert_allclose(segments[4:, 0], far)  # the far rectangle, corner to next corner
    np.testing.assert_allclose(segments[4:, 1], np.roll(far, -1, axis=0))


def test_svg_has_one_frustum_per_camera_and_case(tmp_path):
    rigs, labels = [_rig(), _rig(44.0, 0.01)], ["with priors", "without priors"]
    path = write_layout_svg(tmp_path / "figures" / "layout.svg", rigs, labels)
    assert path.is_file() and not list(path.parent.glob(".*.tmp"))
    root = ET.parse(path).getroot()
    groups = {g.get("id"): g for g in root.iter(f"{SVG}g") if (g.get("id") or "").startswith("layout-")}
    assert set(groups) == {artist_id(k, c) for k in range(2) for c in "ABC"}
    assert all(len(list(g.iter(f"{SVG}path"))) == 8 for g in groups.values())  # 4 edges + 4 sides each
    texts = {"".join(t.itertext()).strip() for t in root.iter(f"{SVG}text")}
    assert set(labels) <= texts and {"A", "B", "C"} <= texts


def test_rigs_and_labels_must_pair_up(tmp_path):
    with pytest.raises(DmaisError, match="2 rig"):
        write_layout_svg(tmp_path / "x.svg", [_rig(), _rig()], ["only one"])
    assert not (tmp_path / "x.svg").exists()
