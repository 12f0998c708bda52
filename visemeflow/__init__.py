"""visemeflow: audio-driven viseme curves for 3D face animation, as a Prefect 3 workflow."""

__version__ = "0.1.0"
