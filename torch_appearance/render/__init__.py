"""Scene description and rendering entry points (one file per scene piece)."""
from .boundary import BoxBoundary, Dielectric, IndexMatched, SDFBoundary
from .emitter import ConstantEnvironment, DiscLight, EnvironmentMap
from .phase import HenyeyGreenstein
from .scene import PathSettings, Scene, SlabScene, default_max_depth, default_rr_depth, derive_seed_grad
from .sensor import FaceTexels, OrthographicCamera, PerspectiveCamera, SurfaceTexels, TexelSensor
from .volpath import render_scene, render_scene_indexed, render_texels

__all__ = ["render_texels", "render_scene", "render_scene_indexed", "Scene", "BoxBoundary", "SDFBoundary", "FaceTexels", "SurfaceTexels",
           "OrthographicCamera", "PerspectiveCamera", "ConstantEnvironment", "EnvironmentMap", "DiscLight",
           "HenyeyGreenstein", "PathSettings", "derive_seed_grad", "SlabScene", "Dielectric", "IndexMatched",
           "TexelSensor", "default_max_depth", "default_rr_depth"]
