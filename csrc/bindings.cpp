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
using ta::volpath::TraceOptions;

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "torch_appearance C++ core: differentiable heterogeneous-volume path tracer (see csrc/volpath/volpath.h)";
  m.attr("source_hash") = TA_SOURCE_HASH;
  m.attr("torch_version") = TA_TORCH_VERSION;

  py::class_<TraceOptions>(m, "TraceOptions")
      .def(py::init<>())
      .def_readwrite("voxel_size", &TraceOptions::voxel_size)
      .def_readwrite("face", &TraceOptions::face)
      .def_readwrite("g", &TraceOptions::g)
      .def_readwrite("ior", &TraceOptions::ior)
      .def_readwrite("environment", &TraceOptions::environment)
      .def_readwrite("spp", &TraceOptions::spp)
      .def_readwrite("seed", &TraceOptions::seed)
      .def_readwrite("max_depth", &TraceOptions::max_depth)
      .def_readwrite("rr_depth", &TraceOptions::rr_depth)
      .def_readwrite("lanes", &TraceOptions::lanes);

  py::class_<ta::volpath::ForwardCounts>(m, "ForwardCounts")
      .def_readonly("scatter_events", &ta::volpath::ForwardCounts::scatter_events)
      .def_readonly("truncated_paths", &ta::volpath::ForwardCounts::truncated_paths);

  m.def("volpath_forward", &ta::volpath::forward_cpu, py::arg("sigma_t"), py::arg("albedo"),
        py::arg("ref_sigma_t"), py::arg("ref_albedo"), py::arg("ratio"), py::arg("options"),
        py::call_guard<py::gil_scoped_release>(),
        "Texel radiance (F, H, W, 3) (or (H, W, 3) for one face) and ForwardCounts.");
  m.def("volpath_backward", &ta::volpath::backward_cpu, py::arg("grad_output"), py::arg("sigma_t"),
        py::arg("albedo"), py::arg("ref_sigma_t"), py::arg("ref_albedo"), py::arg("need_sigma_t"),
        py::arg("need_albedo"), py::arg("options"), py::call_guard<py::gil_scoped_release>(),
        "Radiative backpropagation by path replay: (grad_sigma_t, grad_albedo, scatter events).");
}
