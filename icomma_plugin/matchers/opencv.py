"""Classical matchers from OpenCV.

SIFT with Lowe's ratio test, ORB with cross-checked Hamming matching.

OpenCV keypoints already put pixel centres at integer coordinates (the 3DGS convention).
"""
from __future__ import annotations

import numpy as np
import torch

from .base import Matcher, Matches
from ..checks import check_int


def _to_gray_u8(image: torch.Tensor) -> np.ndarray:
    w = image.new_tensor((0.299, 0.587, 0.114)).view(3, 1, 1)
    g = (image * w).sum(0).clamp(0, 1).mul(255.0).round()
    return g.to(torch.uint8).cpu().numpy()


def _cv2():
    import cv2

    return cv2


def _as_matches(kp0, kp1, pairs, conf, device) -> Matches:
    if not pairs:
        return Matches.empty(device)
    a = np.array([kp0[i].pt for i, _ in pairs], dtype=np.float32)
    b = np.array([kp1[j].pt for _, j in pairs], dtype=np.float32)
    return Matches(torch.from_numpy(a).to(device), torch.from_numpy(b).to(device),
                   torch.tensor(conf, dtype=torch.float32, device=device))


class SiftMatcher(Matcher):
    """OpenCV SIFT + L2 brute force + ratio test. Confidence = 1 - d1/d2.

    Args:
        ratio: Lowe's ratio (a match needs d1 < ratio * d2).
        max_keypoints: SIFT `nfeatures` (0 = all). contrast_threshold: SIFT contrast threshold.
        mutual: also require the match to be the nearest neighbour in the other direction.
    """

    name = "sift"
    python_modules = {"cv2": "opencv-python-headless"}

    def __init__(self, ratio: float = 0.8, max_keypoints: int = 0, contrast_threshold: float = 0.04,
                 mutual: bool = False, **kwargs):
        super().__init__(**kwargs)
        if not isinstance(ratio, (int, float)) or not 0.0 < ratio <= 1.0:
            raise ValueError(f"ratio must be in (0, 1], got {ratio!r}")
        self.ratio = float(ratio)
        self.max_keypoints = int(max_keypoints)
        self.contrast_threshold = float(contrast_threshold)
        self.mutual = bool(mutual)

    def _match(self, image0, image1) -> Matches:
        cv2 = _cv2()
        sift = cv2.SIFT_create(
            nfeatures=self.max_keypoints, contrastThreshold=self.contrast_threshold
        )
        kp0, d0 = sift.detectAndCompute(_to_gray_u8(image0), None)
        kp1, d1 = sift.detectAndCompute(_to_gray_u8(image1), None)
        if d0 is None or d1 is None or len(kp0) < 1 or len(kp1) < 2:
            return Matches.empty(image0.device)
        bf = cv2.BFMatcher(cv2.NORM_L2)
        knn = bf.knnMatch(d0, d1, k=2)
        back = None
        if self.mutual:
            back = {m.queryIdx: m.trainIdx for m in bf.match(d1, d0)}
        pairs, conf = [], []
        for cand in knn:
            if len(cand) < 2:
                continue
            m, n = cand
            if m.distance < self.ratio * n.distance:
                if back is not None and back.get(m.trainIdx) != m.queryIdx:
                    continue
                pairs.append((m.queryIdx, m.trainIdx))
                conf.append(1.0 - m.distance / max(n.distance, 1e-12))
        return _as_matches(kp0, kp1, pairs, conf, image0.device)


class OrbMatcher(Matcher):
    """OpenCV ORB + cross-checked Hamming brute force. Confidence = 1 - distance / 256.

    Args:
        max_keypoints: ORB `nfeatures`.
        max_distance: reject matches with a Hamming distance above it.
        fast_threshold: ORB FAST threshold (lower finds more corners on smooth renders).
    """

    name = "orb"
    python_modules = {"cv2": "opencv-python-headless"}

    def __init__(
        self, max_keypoints: int = 5000, max_distance: int = 64, fast_threshold: int = 10, **kwargs
    ):
        super().__init__(**kwargs)
        check_int(max_keypoints, "max_keypoints", 1)
        self.max_keypoints = max_keypoints
        self.max_distance = int(max_distance)
        self.fast_threshold = int(fast_threshold)

    def _match(self, image0, image1) -> Matches:
        cv2 = _cv2()
        orb = cv2.ORB_create(nfeatures=self.max_keypoints, fastThreshold=self.fast_threshold)
        kp0, d0 = orb.detectAndCompute(_to_gray_u8(image0), None)
        kp1, d1 = orb.detectAndCompute(_to_gray_u8(image1), None)
        if d0 is None or d1 is None:
            return Matches.empty(image0.device)
        bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        pairs, conf = [], []
        for m in bf.match(d0, d1):
            if m.distance <= self.max_distance:
                pairs.append((m.queryIdx, m.trainIdx))
                conf.append(1.0 - m.distance / 256.0)
        return _as_matches(kp0, kp1, pairs, conf, image0.device)
