"""Procedural tabletop scenes with ground truth: the embedded default scene."""

from phirie_jax.synthetic.scene import PRESETS, SynthConfig, SyntheticScene, build_scene, synthesize

__all__ = ["PRESETS", "SynthConfig", "SyntheticScene", "build_scene", "synthesize"]
