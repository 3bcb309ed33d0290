#include "embree_scene.hpp"

#include <cstring>

#include "blockhash_cl/error.hpp"

namespace bhcl::render {

namespace {
const char* rtc_error_name(RTCError code) {
  switch (code) {
    case RTC_ERROR_NONE: return "RTC_ERROR_NONE";
    case RTC_ERROR_UNKNOWN: return "RTC_ERROR_UNKNOWN";
    case RTC_ERROR_INVALID_ARGUMENT: return "RTC_ERROR_INVALID_ARGUMENT";
    case RTC_ERROR_INVALID_OPERATION: return "RTC_ERROR_INVALID_OPERATION";
    case RTC_ERROR_OUT_OF_MEMORY: return "RTC_ERROR_OUT_OF_MEMORY";
    case RTC_ERROR_UNSUPPORTED_CPU: return "RTC_ERROR_UNSUPPORTED_CPU";
    case RTC_ERROR_CANCELLED: return "RTC_ERROR_CANCELLED";
  }
  return "RTC_ERROR(?)";
}
}  // namespace

void EmbreeScene::error_callback(void* user, RTCError code, const char* str) {
  auto* self = static_cast<EmbreeScene*>(user);
  std::lock_guard<std::mutex> lock(self->error_mutex_);
  // Keep the first error: later ones are usually consequences.
  if (self->error_.empty())
    self->error_ = std::string(rtc_error_name(code)) + ": " + (str ? str : "(no message)");
}

void EmbreeScene::check(const char* where) const {
  std::lock_guard<std::mutex> lock(error_mutex_);
  if (error_.empty()) return;
  std::string e = std::move(error_);
  error_.clear();
  throw Error(std::string("Embree error in ") + where + ": " + e);
}

EmbreeScene::EmbreeScene(const Scene& scene, int threads) : scene_(scene) {
  scene.validate();
  std::string config = threads > 0 ? "threads=" + std::to_string(threads) : std::string();
  device_ = rtcNewDevice(config.empty() ? nullptr : config.c_str());
  if (!device_)
    throw Error(std::string("Embree: rtcNewDevice failed: ") + rtc_error_name(rtcGetDeviceError(nullptr)));
  rtcSetDeviceErrorFunction(device_, &EmbreeScene::error_callback, this);
  try {
    rtc_scene_ = rtcNewScene(device_);
    RTCGeometry geom = rtcNewGeometry(device_, RTC_GEOMETRY_TYPE_TRIANGLE);
    auto* vb = static_cast<float*>(rtcSetNewGeometryBuffer(
        geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 3 * sizeof(float), scene.vertices.size()));
    auto* ib = static_cast<unsigned*>(rtcSetNewGeometryBuffer(
        geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(unsigned), scene.triangles.size()));
    check("rtcSetNewGeometryBuffer");
    for (std::size_t i = 0; i < scene.vertices.size(); ++i) {
      vb[3 * i] = scene.vertices[i].x;
      vb[3 * i + 1] = scene.vertices[i].y;
      vb[3 * i + 2] = scene.vertices[i].z;
    }
    for (std::size_t i = 0; i < scene.triangles.size(); ++i)
      std::memcpy(ib + 3 * i, scene.triangles[i].data(), 3 * sizeof(unsigned));
    rtcCommitGeometry(geom);
    rtcAttachGeometry(rtc_scene_, geom);
    rtcReleaseGeometry(geom);
    rtcSetSceneBuildQuality(rtc_scene_, RTC_BUILD_QUALITY_HIGH);
    rtcCommitScene(rtc_scene_);
    check("scene commit");
  } catch (...) {
    if (rtc_scene_) rtcReleaseScene(rtc_scene_);
    rtcReleaseDevice(device_);
    throw;
  }
  epsilon_ = 1e-4f * std::fmax(scene.diagonal(), 1e-3f);
}

EmbreeScene::~EmbreeScene() {
  if (rtc_scene_) rtcReleaseScene(rtc_scene_);
  if (device_) rtcReleaseDevice(device_);
}

bool EmbreeScene::intersect(Vec3 org, Vec3 dir, float tnear, float tfar, Hit& hit) const {
  RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
  RTCRayHit rh;
  set_ray(rh, org, dir, tnear, tfar);
  rtcIntersect1(rtc_scene_, &ctx, &rh);
  if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return false;
  hit.t = rh.ray.tfar;
  hit.prim = rh.hit.primID;
  return true;
}

bool EmbreeScene::inside_glass(Vec3 p) const {
  const Vec3 up{0, 1, 0};
  int depth = 0;
  float t = 0;
  Hit hit;
  for (int n = 0; n < 4096 && intersect(p, up, t, INFINITY, hit); ++n) {
    if (scene_.material_of(hit.prim).type == MaterialType::Glass)
      depth += dot(scene_.geometric_normal(hit.prim), up) < 0 ? -1 : 1;  // front: entering
    t = hit.t + epsilon_;
  }
  return depth > 0;
}

void EmbreeScene::intersect_stream(RTCRayHit* rays, std::size_t n, bool coherent) const {
  if (n == 0) return;
  RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
  ctx.flags = coherent ? RTC_INTERSECT_CONTEXT_FLAG_COHERENT : RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT;
  rtcIntersect1M(rtc_scene_, &ctx, rays, static_cast<unsigned>(n), sizeof(RTCRayHit));
}

void EmbreeScene::occluded_stream(RTCRay* rays, std::size_t n) const {
  if (n == 0) return;
  RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
  ctx.flags = RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT;
  rtcOccluded1M(rtc_scene_, &ctx, rays, static_cast<unsigned>(n), sizeof(RTCRay));
}

void EmbreeScene::intersect16(const int* valid, RTCRayHit16& rays) const {
  RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
  ctx.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
  rtcIntersect16(valid, rtc_scene_, &ctx, &rays);
}

}  // namespace bhcl::render
