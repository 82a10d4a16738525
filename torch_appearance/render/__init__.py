"""Scene description and rendering entry points (one file per scene piece)."""
from .boundary import BoxBoundary, SDFBoundary
from .emitter import ConstantEnvironment, DiscLight, EnvironmentMap
from .phase import HenyeyGreenstein
from .scene import PathSettings, Scene, default_max_depth, default_rr_depth, derive_seed_grad
from .sensor import FaceTexels, OrthographicCamera, PerspectiveCamera, SurfaceTexels
from .trace_job import TraceJob
from .volpath import render_scene, render_scene_indexed, render_texels

__all__ = ["render_texels", "render_scene", "render_scene_indexed", "Scene", "TraceJob", "BoxBoundary", "SDFBoundary",
           "FaceTexels", "SurfaceTexels", "OrthographicCamera", "PerspectiveCamera", "ConstantEnvironment",
           "EnvironmentMap", "DiscLight", "HenyeyGreenstein", "PathSettings", "derive_seed_grad", "default_max_depth",
           "default_rr_depth"]
