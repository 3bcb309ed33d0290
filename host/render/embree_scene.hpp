// The scene loaded into Embree 3: one triangle mesh, committed once, with the device's error
// callback recording errors so that every call site can turn them into a bhcl::Error.
#pragma once

#include <embree3/rtcore.h>

#include <cstddef>
#include <mutex>
#include <string>

#include "scene.hpp"

namespace bhcl::render {

class EmbreeScene {
 public:
  // threads = 0: Embree's default (all cores) for the BVH build.
  explicit EmbreeScene(const Scene& scene, int threads = 0);
  ~EmbreeScene();
  EmbreeScene(const EmbreeScene&) = delete;
  EmbreeScene& operator=(const EmbreeScene&) = delete;

  const Scene& scene() const { return scene_; }
  RTCScene handle() const { return rtc_scene_; }
  // Origin offset along the normal for secondary rays, scaled to the scene (mm for the Cornell
  // Box): keeps a ray from hitting the surface it leaves.
  float ray_epsilon() const { return epsilon_; }

  struct Hit {
    float t = 0;
    std::uint32_t prim = 0;
  };
  // Closest hit of one ray within (tnear, tfar); false on a miss.
  bool intersect(Vec3 org, Vec3 dir, float tnear, float tfar, Hit& hit) const;
  // Whether p lies inside glass: the glass surfaces a ray from p straight up (+y) crosses from
  // their back (inside) minus those it crosses from their front, > 0. Glass faces face outwards,
  // so this holds for closed glass and for glass open at the bottom (a block standing on the
  // floor). Paths start in the medium this gives (camera, emitters) and track it across refractions.
  bool inside_glass(Vec3 p) const;
  // Streams (rtcIntersect1M / rtcOccluded1M); coherent for camera-like ray sets.
  void intersect_stream(RTCRayHit* rays, std::size_t n, bool coherent) const;
  void occluded_stream(RTCRay* rays, std::size_t n) const;
  // A packet of 16 rays (rtcIntersect16); valid[i] = -1 for active lanes, 0 for inactive.
  void intersect16(const int* valid, RTCRayHit16& rays) const;

  // Throws bhcl::Error when Embree reported an error since the last check.
  void check(const char* where) const;

 private:
  static void error_callback(void* user, RTCError code, const char* str);

  const Scene& scene_;
  RTCDevice device_ = nullptr;
  RTCScene rtc_scene_ = nullptr;
  float epsilon_ = 1e-3f;
  mutable std::mutex error_mutex_;
  mutable std::string error_;
};

// Fills a single RTCRay (an occlusion ray, or the ray of an RTCRayHit) for a stream.
inline void set_shadow_ray(RTCRay& r, Vec3 org, Vec3 dir, float tnear, float tfar) {
  r.org_x = org.x;
  r.org_y = org.y;
  r.org_z = org.z;
  r.dir_x = dir.x;
  r.dir_y = dir.y;
  r.dir_z = dir.z;
  r.tnear = tnear;
  r.tfar = tfar;
  r.time = 0;
  r.mask = 0xFFFFFFFFu;
  r.id = 0;
  r.flags = 0;
}

// Fills a single RTCRayHit for a stream: its ray, and its hit as none yet.
inline void set_ray(RTCRayHit& r, Vec3 org, Vec3 dir, float tnear, float tfar) {
  set_shadow_ray(r.ray, org, dir, tnear, tfar);
  r.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  r.hit.primID = RTC_INVALID_GEOMETRY_ID;
  r.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
}

}  // namespace bhcl::render
