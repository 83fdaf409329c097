// Python bindings of the native CPU kernels (one extension module, built by agg/render/native.py).
#include <torch/extension.h>

#include <vector>

std::vector<torch::Tensor> forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor colors,
                                   torch::Tensor opacities, torch::Tensor thresholds, torch::Tensor depths,
                                   torch::Tensor visible, int64_t W, int64_t H);
std::vector<torch::Tensor> backward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor colors,
                                    torch::Tensor opacities, torch::Tensor thresholds, torch::Tensor depths,
                                    torch::Tensor visible, int64_t W, int64_t H, torch::Tensor T_final,
                                    torch::Tensor last, torch::Tensor grad_accum, torch::Tensor grad_alpha);
std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                           torch::Tensor viewmat, torch::Tensor K, int64_t W, int64_t H,
                                           double near);
std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                            torch::Tensor viewmat, torch::Tensor K, int64_t W, int64_t H,
                                            double near, torch::Tensor g_means2d, torch::Tensor g_conics,
                                            torch::Tensor g_depths);

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &forward, "Composite screen-space Gaussians (forward)");
  m.def("backward", &backward, "Composite screen-space Gaussians (backward)");
  m.def("project_forward", &project_forward, "EWA projection of 3D Gaussians (forward)");
  m.def("project_backward", &project_backward, "EWA projection of 3D Gaussians (backward)");
}
