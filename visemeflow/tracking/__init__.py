"""Tracking: video and landmark sources, camera, rendering, optical flow, the loss terms of Eq. 1-8 and solvers.

`landmarks` reads 2D facial landmark files (OpenFace, MediaPipe FaceMesh, generic 68-point) into one 68-point
Multi-PIE layout and runs OpenCV Facemark LBF; `video` decodes and encodes video and its audio track with PyAV.
"""
