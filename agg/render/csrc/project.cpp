// EWA projection of 3D Gaussians on the CPU (C++ / OpenMP), forward and hand-derived backward.
//
// The plain-torch twin is project_gaussians() in agg/render/projection.py (autograd); the tests in
// tests/test_render_project.py compare the two on values and on the gradients of means, quats, scales and the view
// matrix. Every formula below mirrors that function line by line:
//
//   p = R_v m + t_v;  iz = 1 / max(z, near);  t = clamp(x iz, -lx_neg, lx_pos), clamp(y iz, ...)
//   J = [[fx iz, 0, -fx tx iz], [0, fy iz, -fy ty iz]];  M = R_v R(q / |q|) diag(s);  A = J M  (rows a0, a1)
//   cov = A A^T;  det = |a0 x a1|^2 + e (cxx + cyy) + e^2;  conic = [cyy + e, -cxy, cxx + e] / det
//   means2d = [fx x iz + cx, fy y iz + cy];  depth = z

#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace {

constexpr float EPS_2D = 0.3f;
constexpr float FOV_CLAMP = 1.3f;
constexpr float QUAT_EPS2 = 1e-24f;  // (1e-12)^2, as normalize_quats

struct Camera {
  float Rv[9], tv[3];
  float fx, fy, cx, cy;
  float lx_neg, lx_pos, ly_neg, ly_pos;
  float near;
};

Camera make_camera(const torch::Tensor& viewmat, const torch::Tensor& K, int64_t W, int64_t H, double near) {
  Camera c;
  auto v = viewmat.accessor<float, 2>();
  auto k = K.accessor<float, 2>();
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) c.Rv[3 * i + j] = v[i][j];
    c.tv[i] = v[i][3];
  }
  c.fx = k[0][0];
  c.fy = k[1][1];
  c.cx = k[0][2];
  c.cy = k[1][2];
  const float mx = (FOV_CLAMP - 1.0f) * 0.5f * float(W) / c.fx;
  const float my = (FOV_CLAMP - 1.0f) * 0.5f * float(H) / c.fy;
  c.lx_neg = -(c.cx / c.fx + mx);
  c.lx_pos = (float(W) - c.cx) / c.fx + mx;
  c.ly_neg = -(c.cy / c.fy + my);
  c.ly_pos = (float(H) - c.cy) / c.fy + my;
  c.near = float(near);
  return c;
}

inline void rotmat(const float q[4], float R[9]) {
  const float w = q[0], x = q[1], y = q[2], z = q[3];
  R[0] = 1 - 2 * (y * y + z * z);
  R[1] = 2 * (x * y - w * z);
  R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z);
  R[4] = 1 - 2 * (x * x + z * z);
  R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y);
  R[7] = 2 * (y * z + w * x);
  R[8] = 1 - 2 * (x * x + y * y);
}

// Everything the backward pass needs for one Gaussian, recomputed from the inputs.
struct Fwd {
  float p[3];        // camera-frame mean
  float iz;          // 1 / max(z, near)
  float u, v;        // x iz, y iz (before clamping)
  float tx, ty;      // clamped ratios
  float j00, j02, j11, j12;
  float qn[4], qnorm;
  bool q_clamped;
  float R[9], RvR[9], M[9];  // row-major 3x3
  float a0[3], a1[3];
  float cxx, cxy, cyy, cr[3], det;
  float conic[3];
  float means2d[2];
};

inline void forward_one(const Camera& c, const float* m, const float* q, const float* s, Fwd& f) {
  for (int i = 0; i < 3; ++i)
    f.p[i] = c.Rv[3 * i] * m[0] + c.Rv[3 * i + 1] * m[1] + c.Rv[3 * i + 2] * m[2] + c.tv[i];
  const float zc = std::max(f.p[2], c.near);
  f.iz = 1.0f / zc;
  f.u = f.p[0] * f.iz;
  f.v = f.p[1] * f.iz;
  f.tx = std::min(std::max(f.u, c.lx_neg), c.lx_pos);
  f.ty = std::min(std::max(f.v, c.ly_neg), c.ly_pos);
  f.j00 = c.fx * f.iz;
  f.j02 = -c.fx * f.tx * f.iz;
  f.j11 = c.fy * f.iz;
  f.j12 = -c.fy * f.ty * f.iz;

  const float n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
  f.q_clamped = !(n2 >= QUAT_EPS2);
  f.qnorm = std::sqrt(f.q_clamped ? QUAT_EPS2 : n2);
  for (int i = 0; i < 4; ++i) f.qn[i] = q[i] / f.qnorm;
  rotmat(f.qn, f.R);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      f.RvR[3 * i + j] = c.Rv[3 * i] * f.R[j] + c.Rv[3 * i + 1] * f.R[3 + j] + c.Rv[3 * i + 2] * f.R[6 + j];
      f.M[3 * i + j] = f.RvR[3 * i + j] * s[j];
    }
  for (int j = 0; j < 3; ++j) {
    f.a0[j] = f.j00 * f.M[j] + f.j02 * f.M[6 + j];
    f.a1[j] = f.j11 * f.M[3 + j] + f.j12 * f.M[6 + j];
  }
  f.cxx = f.a0[0] * f.a0[0] + f.a0[1] * f.a0[1] + f.a0[2] * f.a0[2];
  f.cxy = f.a0[0] * f.a1[0] + f.a0[1] * f.a1[1] + f.a0[2] * f.a1[2];
  f.cyy = f.a1[0] * f.a1[0] + f.a1[1] * f.a1[1] + f.a1[2] * f.a1[2];
  f.cr[0] = f.a0[1] * f.a1[2] - f.a0[2] * f.a1[1];
  f.cr[1] = f.a0[2] * f.a1[0] - f.a0[0] * f.a1[2];
  f.cr[2] = f.a0[0] * f.a1[1] - f.a0[1] * f.a1[0];
  f.det = (f.cr[0] * f.cr[0] + f.cr[1] * f.cr[1] + f.cr[2] * f.cr[2]) + EPS_2D * (f.cxx + f.cyy) + EPS_2D * EPS_2D;
  const float inv_det = 1.0f / f.det;
  f.conic[0] = (f.cyy + EPS_2D) * inv_det;
  f.conic[1] = -f.cxy * inv_det;
  f.conic[2] = (f.cxx + EPS_2D) * inv_det;
  f.means2d[0] = c.fx * f.p[0] * f.iz + c.cx;
  f.means2d[1] = c.fy * f.p[1] * f.iz + c.cy;
}

inline void check(const torch::Tensor& t, int64_t cols, const char* name) {
  TORCH_CHECK(t.dtype() == torch::kFloat32 && t.is_contiguous() && t.dim() == 2 && t.size(1) == cols, name,
              " must be a contiguous float32 [N, ", cols, "] tensor");
}

}  // namespace

// Returns {means2d [N, 2], conics [N, 3], depths [N]}.
std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                           torch::Tensor viewmat, torch::Tensor K, int64_t W, int64_t H,
                                           double near) {
  check(means, 3, "means");
  check(quats, 4, "quats");
  check(scales, 3, "scales");
  const int64_t N = means.size(0);
  const Camera c = make_camera(viewmat, K, W, H, near);
  auto means2d = torch::empty({N, 2}, means.options());
  auto conics = torch::empty({N, 3}, means.options());
  auto depths = torch::empty({N}, means.options());
  const float *m = means.data_ptr<float>(), *q = quats.data_ptr<float>(), *s = scales.data_ptr<float>();
  float *o2 = means2d.data_ptr<float>(), *oc = conics.data_ptr<float>(), *od = depths.data_ptr<float>();
#pragma omp parallel for schedule(static)
  for (int64_t g = 0; g < N; ++g) {
    Fwd f;
    forward_one(c, m + 3 * g, q + 4 * g, s + 3 * g, f);
    o2[2 * g] = f.means2d[0];
    o2[2 * g + 1] = f.means2d[1];
    for (int i = 0; i < 3; ++i) oc[3 * g + i] = f.conic[i];
    od[g] = f.p[2];
  }
  return {means2d, conics, depths};
}

// Given dL/dmeans2d [N, 2], dL/dconics [N, 3], dL/ddepths [N], returns
// {dL/dmeans [N, 3], dL/dquats [N, 4], dL/dscales [N, 3], dL/dviewmat [4, 4]}.
std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                            torch::Tensor viewmat, torch::Tensor K, int64_t W, int64_t H,
                                            double near, torch::Tensor g_means2d, torch::Tensor g_conics,
                                            torch::Tensor g_depths) {
  const int64_t N = means.size(0);
  const Camera c = make_camera(viewmat, K, W, H, near);
  auto gm_out = torch::zeros({N, 3}, means.options());
  auto gq_out = torch::zeros({N, 4}, means.options());
  auto gs_out = torch::zeros({N, 3}, means.options());
  const float *m = means.data_ptr<float>(), *q = quats.data_ptr<float>(), *s = scales.data_ptr<float>();
  const float *g2 = g_means2d.data_ptr<float>(), *gc = g_conics.data_ptr<float>(), *gd = g_depths.data_ptr<float>();
  float *pm = gm_out.data_ptr<float>(), *pq = gq_out.data_ptr<float>(), *ps = gs_out.data_ptr<float>();
  double gview[12] = {0};  // dL/dR_v (row-major 3x3), dL/dt_v (3)

#pragma omp parallel
  {
    double gv[12] = {0};
#pragma omp for schedule(static)
    for (int64_t gi = 0; gi < N; ++gi) {
      Fwd f;
      forward_one(c, m + 3 * gi, q + 4 * gi, s + 3 * gi, f);
      const float* gcon = gc + 3 * gi;
      // conic = num / det
      const float inv_det = 1.0f / f.det;
      float g_cyy = gcon[0] * inv_det, g_cxy = -gcon[1] * inv_det, g_cxx = gcon[2] * inv_det;
      const float g_det = -(gcon[0] * f.conic[0] + gcon[1] * f.conic[1] + gcon[2] * f.conic[2]) * inv_det;
      g_cxx += EPS_2D * g_det;
      g_cyy += EPS_2D * g_det;
      const float g_cr[3] = {2 * f.cr[0] * g_det, 2 * f.cr[1] * g_det, 2 * f.cr[2] * g_det};
      // cr = a0 x a1: dL/da0 = a1 x g_cr, dL/da1 = g_cr x a0
      float ga0[3] = {f.a1[1] * g_cr[2] - f.a1[2] * g_cr[1], f.a1[2] * g_cr[0] - f.a1[0] * g_cr[2],
                      f.a1[0] * g_cr[1] - f.a1[1] * g_cr[0]};
      float ga1[3] = {g_cr[1] * f.a0[2] - g_cr[2] * f.a0[1], g_cr[2] * f.a0[0] - g_cr[0] * f.a0[2],
                      g_cr[0] * f.a0[1] - g_cr[1] * f.a0[0]};
      for (int j = 0; j < 3; ++j) {
        ga0[j] += 2 * g_cxx * f.a0[j] + g_cxy * f.a1[j];
        ga1[j] += 2 * g_cyy * f.a1[j] + g_cxy * f.a0[j];
      }
      // a0 = j00 M0 + j02 M2, a1 = j11 M1 + j12 M2
      float gM[9];
      float g_j00 = 0, g_j02 = 0, g_j11 = 0, g_j12 = 0;
      for (int j = 0; j < 3; ++j) {
        gM[j] = f.j00 * ga0[j];
        gM[3 + j] = f.j11 * ga1[j];
        gM[6 + j] = f.j02 * ga0[j] + f.j12 * ga1[j];
        g_j00 += ga0[j] * f.M[j];
        g_j02 += ga0[j] * f.M[6 + j];
        g_j11 += ga1[j] * f.M[3 + j];
        g_j12 += ga1[j] * f.M[6 + j];
      }
      // M = RvR diag(s)
      float gRvR[9];
      for (int j = 0; j < 3; ++j) {
        float acc = 0;
        for (int i = 0; i < 3; ++i) {
          acc += gM[3 * i + j] * f.RvR[3 * i + j];
          gRvR[3 * i + j] = gM[3 * i + j] * s[3 * gi + j];
        }
        ps[3 * gi + j] = acc;
      }
      // RvR = Rv R: dL/dR = Rv^T gRvR, dL/dRv += gRvR R^T
      float gR[9];
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
          gR[3 * i + j] = c.Rv[i] * gRvR[j] + c.Rv[3 + i] * gRvR[3 + j] + c.Rv[6 + i] * gRvR[6 + j];
          gv[3 * i + j] += double(gRvR[3 * i] * f.R[3 * j] + gRvR[3 * i + 1] * f.R[3 * j + 1] +
                                  gRvR[3 * i + 2] * f.R[3 * j + 2]);
        }
      // R(qn)
      const float w = f.qn[0], x = f.qn[1], y = f.qn[2], z = f.qn[3];
      const float gqn[4] = {
          2 * (-z * gR[1] + y * gR[2] + z * gR[3] - x * gR[5] - y * gR[6] + x * gR[7]),
          2 * (y * gR[1] + z * gR[2] + y * gR[3] - 2 * x * gR[4] - w * gR[5] + z * gR[6] + w * gR[7] - 2 * x * gR[8]),
          2 * (-2 * y * gR[0] + x * gR[1] + w * gR[2] + x * gR[3] + z * gR[5] - w * gR[6] + z * gR[7] - 2 * y * gR[8]),
          2 * (-2 * z * gR[0] - w * gR[1] + x * gR[2] + w * gR[3] - 2 * z * gR[4] + y * gR[5] + x * gR[6] + y * gR[7]),
      };
      // qn = q / n, n = sqrt(max(|q|^2, eps^2))
      const float dot = f.q_clamped ? 0.0f : (w * gqn[0] + x * gqn[1] + y * gqn[2] + z * gqn[3]);
      for (int i = 0; i < 4; ++i) pq[4 * gi + i] = (gqn[i] - f.qn[i] * dot) / f.qnorm;
      // J entries, clamped ratios, means2d
      const float* gm2 = g2 + 2 * gi;
      float g_iz = c.fx * g_j00 + c.fy * g_j11 - c.fx * f.tx * g_j02 - c.fy * f.ty * g_j12;
      const float g_tx = -c.fx * f.iz * g_j02, g_ty = -c.fy * f.iz * g_j12;
      const float g_u = (f.u > c.lx_neg && f.u < c.lx_pos) ? g_tx : 0.0f;
      const float g_v = (f.v > c.ly_neg && f.v < c.ly_pos) ? g_ty : 0.0f;
      float gp[3];
      gp[0] = g_u * f.iz + gm2[0] * c.fx * f.iz;
      gp[1] = g_v * f.iz + gm2[1] * c.fy * f.iz;
      g_iz += g_u * f.p[0] + g_v * f.p[1] + gm2[0] * c.fx * f.p[0] + gm2[1] * c.fy * f.p[1];
      gp[2] = gd[gi] + ((f.p[2] >= c.near) ? -g_iz * f.iz * f.iz : 0.0f);
      // p = Rv m + tv
      for (int j = 0; j < 3; ++j) pm[3 * gi + j] = c.Rv[j] * gp[0] + c.Rv[3 + j] * gp[1] + c.Rv[6 + j] * gp[2];
      const float* mg = m + 3 * gi;
      for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) gv[3 * i + j] += double(gp[i] * mg[j]);
        gv[9 + i] += double(gp[i]);
      }
    }
#pragma omp critical
    for (int i = 0; i < 12; ++i) gview[i] += gv[i];
  }
  auto g_view = torch::zeros({4, 4}, means.options());
  auto a = g_view.accessor<float, 2>();
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) a[i][j] = float(gview[3 * i + j]);
    a[i][3] = float(gview[9 + i]);
  }
  return {gm_out, gq_out, gs_out, g_view};
}
