// The one binding file: torch_appearance._C. Python wrappers live in torch_appearance/autograd/.
#include <torch/extension.h>

#include "volpath/volpath.h"

#ifndef TA_SOURCE_HASH
#define TA_SOURCE_HASH "unknown"
#endif
#ifndef TA_TORCH_VERSION
#define TA_TORCH_VERSION "unknown"
#endif

namespace py = pybind11;

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "torch_appearance C++ core: differentiable heterogeneous-volume path tracer (see csrc/volpath/volpath.h)";
  m.attr("source_hash") = TA_SOURCE_HASH;
  m.attr("torch_version") = TA_TORCH_VERSION;

  using ta::volpath::BoundaryOptions;
  using ta::volpath::EmitterOptions;
  using ta::volpath::SceneOptions;
  using ta::volpath::SensorOptions;
  // General scenes: one struct per piece (see torch_appearance/render/*.py for the dataclass of each).
  py::class_<BoundaryOptions>(m, "BoundaryOptions")
      .def(py::init<>())
      .def_readwrite("kind", &BoundaryOptions::kind)
      .def_readwrite("ior", &BoundaryOptions::ior)
      .def_readwrite("sdf", &BoundaryOptions::sdf);
  py::class_<SensorOptions>(m, "SensorOptions")
      .def(py::init<>())
      .def_readwrite("kind", &SensorOptions::kind)
      .def_readwrite("face", &SensorOptions::face)
      .def_readwrite("points", &SensorOptions::points)
      .def_readwrite("normals", &SensorOptions::normals)
      .def_readwrite("radius", &SensorOptions::radius)
      .def_readwrite("lift", &SensorOptions::lift)
      .def_readwrite("origin", &SensorOptions::origin)
      .def_readwrite("forward", &SensorOptions::forward)
      .def_readwrite("right", &SensorOptions::right)
      .def_readwrite("up", &SensorOptions::up)
      .def_readwrite("rows", &SensorOptions::rows)
      .def_readwrite("cols", &SensorOptions::cols)
      .def_readwrite("width", &SensorOptions::width)
      .def_readwrite("height", &SensorOptions::height)
      .def_readwrite("tan_half_fov", &SensorOptions::tan_half_fov);
  py::class_<EmitterOptions>(m, "EmitterOptions")
      .def(py::init<>())
      .def_readwrite("kind", &EmitterOptions::kind)
      .def_readwrite("radiance", &EmitterOptions::radiance)
      .def_readwrite("ambient", &EmitterOptions::ambient)
      .def_readwrite("direction", &EmitterOptions::direction)
      .def_readwrite("cos_max", &EmitterOptions::cos_max)
      .def_readwrite("map", &EmitterOptions::map);
  py::class_<SceneOptions>(m, "SceneOptions")
      .def(py::init<>())
      .def_readwrite("voxel_size", &SceneOptions::voxel_size)
      .def_readwrite("origin", &SceneOptions::origin)
      .def_readwrite("g", &SceneOptions::g)
      .def_readwrite("boundary", &SceneOptions::boundary)
      .def_readwrite("sensor", &SceneOptions::sensor)
      .def_readwrite("emitter", &SceneOptions::emitter)
      .def_readwrite("spp", &SceneOptions::spp)
      .def_readwrite("seed", &SceneOptions::seed)
      .def_readwrite("max_depth", &SceneOptions::max_depth)
      .def_readwrite("rr_depth", &SceneOptions::rr_depth)
      .def_readwrite("lanes", &SceneOptions::lanes)
      .def_readwrite("hero", &SceneOptions::hero)
      .def_readwrite("part_rank", &SceneOptions::part_rank)
      .def_readwrite("part_world", &SceneOptions::part_world);

  py::class_<ta::volpath::ForwardCounts>(m, "ForwardCounts")
      .def_readonly("scatter_events", &ta::volpath::ForwardCounts::scatter_events)
      .def_readonly("truncated_paths", &ta::volpath::ForwardCounts::truncated_paths);

  m.def("scene_forward", &ta::volpath::scene_forward_cpu, py::arg("sigma_t"), py::arg("albedo"),
        py::arg("ref_sigma_t"), py::arg("ref_albedo"), py::arg("ratio"), py::arg("options"),
        py::call_guard<py::gil_scoped_release>(),
        "General-scene radiance ((H, W, 3) image, (N, 3) texels, ...) and ForwardCounts.");
  m.def("scene_backward", &ta::volpath::scene_backward_cpu, py::arg("grad_output"), py::arg("sigma_t"),
        py::arg("albedo"), py::arg("ref_sigma_t"), py::arg("ref_albedo"), py::arg("need_sigma_t"),
        py::arg("need_albedo"), py::arg("options"), py::arg("sigma_t_floor") = 0.0, py::arg("albedo_floor") = 0.0,
        py::call_guard<py::gil_scoped_release>(),
        "General-scene path replay: (grad_sigma_t, grad_albedo, scatter events).");
  m.def("scene_forward_indexed", &ta::volpath::scene_forward_indexed_cpu, py::arg("index"),
        py::arg("sigma_t_table"), py::arg("albedo_table"), py::arg("options"), py::call_guard<py::gil_scoped_release>(),
        "General-scene radiance of a palette medium (uint8 index volume, (3, P) tables) and ForwardCounts.");
  m.def("_set_simd", &ta::volpath::set_simd, py::arg("mode"),
        "Test hook: the slab walk, -1 automatic (the CPU and TA_SIMD), 0 scalar, 1 AVX2, 2 AVX-512; returns the one before.");
  m.def("_set_tape_capacity", &ta::volpath::set_tape_capacity, py::arg("segments"),
        "Test-only: initial per-thread tape capacity of the replay (0: every path replays twice); returns the old.");
}
