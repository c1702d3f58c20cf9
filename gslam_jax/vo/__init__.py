"""OpenCV stereo front-end: rectification, dense stereo, stereo VO, fallback fusion."""
