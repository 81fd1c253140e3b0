"""Practitioners' baseline: local features (ORB, AKAZE or SIFT) matched against the map around the estimate,
with a RANSAC similarity transform.

The keypoints' descriptor is the detector's own, or with ``descriptor`` one of the trained descriptors that
``opencv-contrib-python-headless`` compiles in (``DESCRIPTORS``: BEBLID and TEBLID, boosted binary descriptors
learned on image patches; VGG, a learned float descriptor; BoostDesc's BinBoost), computed on the detector's
keypoints with the sampling window their authors give for that detector (``DESCRIPTOR_SCALES``). Their weights
are part of the OpenCV library: nothing is downloaded.

Each step: dead-reckon (the floor's integrator), take the database window around the prediction at the working
resolution (``WindowMatchingAgent``), resize the camera image to the same ground resolution with the measured
altitude (no rotation: the descriptors are rotation-invariant; both enlarged alike when the camera image would
span fewer than ``UPSAMPLE_PX_ACROSS`` pixels, a map coarse for the footprint), detect and describe keypoints on
both, match them (brute force, Lowe's ratio test) and fit a 4-degree-of-freedom similarity (rotation, uniform scale,
translation) with ``cv2.estimateAffinePartial2D`` (RANSAC). The fit is accepted when it has ``min_inliers``
inliers, a scale within ``max_scale_error`` of 1 (both images are at the same ground resolution) and a rotation
within ``max_rotation_error_deg`` of the one the measured heading implies (``CameraModel.scale_rotation``);
the vehicle (the camera's centre pixel) mapped through it is the fix. Otherwise the agent dead-reckons and
says why (status ``"dead_reckoning"``, ``extras["reason"]``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.patches import to_gray
from aerial_loc_env.estimators.protocol import Estimate, Observation
from aerial_loc_env.estimators.template_matching import Fix, Window, WindowMatchingAgent, WindowMatchingParams

DETECTORS = ("orb", "akaze", "sift")
#: trained descriptors of OpenCV's contrib module xfeatures2d -> (factory name, norm to match them with)
DESCRIPTORS = {"beblid": ("BEBLID_create", cv2.NORM_HAMMING), "teblid": ("TEBLID_create", cv2.NORM_HAMMING),
               "vgg": ("VGG_create", cv2.NORM_L2), "boostdesc": ("BoostDesc_create", cv2.NORM_HAMMING)}
#: each descriptor's sampling window for each detector's keypoints (``scale_factor``; OpenCV's documentation)
DESCRIPTOR_SCALES = {
    "beblid": {"orb": 1.0, "sift": 6.75, "akaze": 5.0},
    "teblid": {"orb": 1.0, "sift": 6.75, "akaze": 5.0},
    "vgg": {"orb": 0.75, "sift": 6.75, "akaze": 5.0},
    "boostdesc": {"orb": 0.75, "sift": 6.75, "akaze": 5.0},
}


@dataclass(frozen=True)
class FeatureMatchingParams(WindowMatchingParams):
    detector: str = field(default="orb", metadata=rng(choices=DETECTORS))
    # None: the detector's own descriptor; else a trained one computed on the detector's keypoints
    descriptor: str | None = field(default=None, metadata=rng(choices=tuple(DESCRIPTORS)))
    max_features: int = field(default=2000, metadata=rng(10, 100000, doc="ORB/SIFT keypoint cap per image"))
    ratio: float = field(default=0.8, metadata=rng(0.0, 1.0, lo_open=True, doc="Lowe's ratio test"))
    ransac_threshold_px: float = field(default=3.0, metadata=rng(0.1, 100.0))
    min_inliers: int = field(default=12, metadata=rng(3, 100000))
    max_scale_error: float = field(default=0.2, metadata=rng(0.0, 10.0))
    max_rotation_error_deg: float = field(default=20.0, metadata=rng(0.0, 180.0))


def make_detector(name: str, max_features: int):
    """The OpenCV detector/descriptor and the norm to match its descriptors with."""
    if name == "orb":
        return cv2.ORB_create(nfeatures=max_features), cv2.NORM_HAMMING
    if name == "akaze":
        if not hasattr(cv2, "AKAZE_create"):  # OpenCV 5 moved AKAZE out of the main package
            raise ConfigError(f"feature matching: detector 'akaze' is not in this OpenCV ({cv2.__version__}); "
                              "use 'orb' or 'sift', or install an OpenCV build that has AKAZE")
        return cv2.AKAZE_create(), cv2.NORM_HAMMING
    if name == "sift":
        if not hasattr(cv2, "SIFT_create"):  # pragma: no cover - OpenCV < 4.4
            raise ConfigError(f"feature matching: detector 'sift' is not in this OpenCV ({cv2.__version__}); "
                              "use 'orb'")
        return cv2.SIFT_create(nfeatures=max_features), cv2.NORM_L2
    raise ConfigError(f"feature matching: unknown detector {name!r}; use one of {DETECTORS}")


def make_descriptor(name: str, detector: str):
    """A trained descriptor extractor for ``detector``'s keypoints and the norm to match it with."""
    if name not in DESCRIPTORS:
        raise ConfigError(f"feature matching: unknown descriptor {name!r}; use one of {', '.join(DESCRIPTORS)} "
                          "(or leave descriptor unset for the detector's own)")
    factory, norm = DESCRIPTORS[name]
    create = getattr(getattr(cv2, "xfeatures2d", None), factory, None)
    if create is None:
        raise ConfigError(f"feature matching: descriptor {name!r} needs OpenCV's contrib module (cv2.xfeatures2d."
                          f"{factory}), which this OpenCV ({cv2.__version__}) lacks; install "
                          "opencv-contrib-python-headless in place of opencv-python-headless (same version)")
    return create(scale_factor=DESCRIPTOR_SCALES[name][detector]), norm


class FeatureMatchingAgent(WindowMatchingAgent):
    """ORB/AKAZE/SIFT keypoints (their own or a trained descriptor) matched between the camera image and the map
    window, RANSAC similarity."""

    Params = FeatureMatchingParams
    #: ``work_gsd_m = None``: this many pixels across the footprint's short side (the paper's 100 m footprint
    #: gives 0.5 m); the keypoints' 31-pixel patches then fit in the camera image at any geometry
    AUTO_PX_ACROSS = 200

    def auto_work_gsd_m(self, briefing) -> float:
        """As the template matcher's, and never finer than the camera's own pixels (no invented detail)."""
        return max(super().auto_work_gsd_m(briefing), briefing.camera.gsd_m(briefing.altitude_m))

    def __init__(self, params: FeatureMatchingParams | None = None) -> None:
        super().__init__(params)
        self.detector, norm = make_detector(self.params.detector, self.params.max_features)
        self.extractor = None
        if self.params.descriptor is not None:
            self.extractor, norm = make_descriptor(self.params.descriptor, self.params.detector)
        self.matcher = cv2.BFMatcher(norm)

    def _features(self, gray: np.ndarray):
        img = np.clip(gray, 0, 255).astype(np.uint8)
        if self.extractor is None:
            return self.detector.detectAndCompute(img, None)
        return self.extractor.compute(img, self.detector.detect(img, None))

    #: the working images are enlarged (camera and map window alike) until the camera's spans this many pixels
    #: across its short side, when a map coarse for the footprint leaves fewer (RealMap's 25 m footprint over a
    #: 0.3 m map: 83 px, where ORB's 31-pixel patches and 8-level pyramid find almost no keypoints); never beyond
    #: the camera's own pixels, and not for less than MIN_UPSAMPLING (the paper's geometry: 200 px, no change)
    UPSAMPLE_PX_ACROSS = 200
    MIN_UPSAMPLING = 1.25

    def upsampling(self, size: tuple[int, int], camera_gsd_m: float) -> float:
        """The factor the working images of a frame are enlarged by (1: none; see ``UPSAMPLE_PX_ACROSS``)."""
        up = min(self.UPSAMPLE_PX_ACROSS / min(size), min(self.level_gsd) / camera_gsd_m)
        return up if up >= self.MIN_UPSAMPLING else 1.0

    def match(self, obs: Observation, pred: Estimate, window: Window) -> Fix | str:
        p: FeatureMatchingParams = self.params
        cam = self.camera
        gsd_u = cam.gsd_m(obs.altitude_m)
        fx, fy = gsd_u / self.level_gsd[0], gsd_u * cam.pixel_aspect / self.level_gsd[1]
        size = (max(8, int(round(cam.width_px * fx))), max(8, int(round(cam.height_px * fy))))
        up = self.upsampling(size, gsd_u)
        map_image, threshold, to_level = window.image, p.ransac_threshold_px, (1.0, 1.0)
        if up > 1.0:   # both images at the same finer sampling; fits mapped back to working-level pixels
            size = (int(round(size[0] * up)), int(round(size[1] * up)))
            h, w = window.image.shape
            enlarged = (int(round(w * up)), int(round(h * up)))
            map_image = cv2.resize(window.image, enlarged, interpolation=cv2.INTER_LINEAR)
            to_level, threshold = (w / enlarged[0], h / enlarged[1]), p.ransac_threshold_px * up
        small = cv2.resize(to_gray(obs.image), size, interpolation=cv2.INTER_AREA)
        kc, dc = self._features(small)
        kw, dw = self._features(map_image)
        if dc is None or dw is None or len(kc) < 2 or len(kw) < 2:
            return "no match: too few keypoints"
        pairs = self.matcher.knnMatch(dc, dw, k=2)
        good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < p.ratio * m[1].distance]
        if len(good) < p.min_inliers:
            return f"no match: {len(good)} ratio-test matches < min_inliers {p.min_inliers}"
        src = np.float32([kc[m.queryIdx].pt for m in good])
        dst = np.float32([kw[m.trainIdx].pt for m in good])
        # OpenCV's RANSAC seeds its own generator identically on every call: deterministic
        model, inliers = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=threshold)
        if model is None:
            return "no match: RANSAC found no similarity"
        n_in = int(inliers.sum())
        scale = math.hypot(model[0, 0], model[1, 0])
        rot = math.atan2(model[1, 0], model[0, 0])
        _, r = cam.scale_rotation(self.orthomap, obs.yaw_rad, obs.altitude_m)
        expected = math.atan2(r[1, 0], r[0, 0])
        rot_err = abs(math.degrees(math.atan2(math.sin(rot - expected), math.cos(rot - expected))))
        extras = {"inliers": n_in, "matches": len(good), "scale": scale, "rotation_error_deg": rot_err}
        if up > 1.0:
            extras["upsampling"] = up
        if n_in < p.min_inliers:
            return f"no match: {n_in} RANSAC inliers < min_inliers {p.min_inliers}"
        if abs(scale - 1.0) > p.max_scale_error:
            return f"no match: similarity scale {scale:.2f} is not 1 +- {p.max_scale_error}"
        if rot_err > p.max_rotation_error_deg:
            return f"no match: rotation {rot_err:.0f} deg off the measured heading"
        cu, cv = cam.center_px
        centre = np.array([(cu + 0.5) * size[0] / cam.width_px - 0.5,
                           (cv + 0.5) * size[1] / cam.height_px - 0.5, 1.0])
        u, v = model @ centre
        if up > 1.0:
            u, v = (u + 0.5) * to_level[0] - 0.5, (v + 0.5) * to_level[1] - 0.5
        x, y = self.level_point_to_world(window.u0 + u, window.v0 + v)
        return Fix(x, y, extras)
