"""Radar landmarks on polar scans: the Cen 2018 detector (keypoints for pose estimation)."""

from reradar_core.landmarks.cen2018 import Cen2018Config, Landmarks, cen2018_response, detect_landmarks

__all__ = ["Cen2018Config", "Landmarks", "cen2018_response", "detect_landmarks"]
