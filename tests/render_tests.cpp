// The photon-mapping renderer (host/render): determinism, energy conservation on a furnace
// scene, EXR round trip, exact methods agreeing, scene-file errors and the `bhcl render` command.
#ifdef BHCL_HAVE_RENDER

#include "test_util.hpp"

#include <sys/stat.h>

#include <nlohmann/json.hpp>

#include "compare.hpp"
#include "embree_scene.hpp"
#include "exr_io.hpp"
#include "final_gather.hpp"
#include "path_trace.hpp"
#include "photon_trace.hpp"
#include "png_io.hpp"
#include "progressive.hpp"
#include "scene.hpp"

using namespace bhcl;
using namespace bhcl::render;

namespace {

// The photon maps of a scene: `photons` traced with `seed` on `threads` threads; `method`
// (non-empty) indexes the global map and the caustic one where there is one.
PhotonMaps trace_photons(const EmbreeScene& es, const LightSampler& lights, std::size_t photons,
                         std::uint64_t seed, int threads, const std::string& method = "") {
  PhotonTraceOptions po;
  po.photons = photons;
  po.seed = seed;
  po.threads = threads;
  PhotonMaps maps = build_photon_maps(es, lights, po);
  if (!method.empty()) {
    maps.global->build_index(method, test::runtime());
    if (maps.caustic) maps.caustic->build_index(method, test::runtime());
  }
  return maps;
}

// A small render's options: size x size pixels, `gather` rays and k neighbours per point.
RenderOptions small_options(int size, int gather, int k, std::uint64_t seed, int threads, int shadow_rays = 2,
                            int spp = 1) {
  RenderOptions ro;
  ro.width = ro.height = size;
  ro.gather = gather;
  ro.shadow_rays = shadow_rays;
  ro.spp = spp;
  ro.search.k = k;
  ro.seed = seed;
  ro.threads = threads;
  return ro;
}

struct SmallRender {
  Image image;
  RenderStats stats;
  std::size_t photons = 0, caustic_photons = 0;
  bool has_caustic_map = false;
};

SmallRender small_render(const Scene& scene, const std::string& method, std::size_t photons, int size,
                         int gather, int threads, std::uint64_t seed = 7, int k = 16,
                         int shadow_rays = 2, int spp = 1) {
  EmbreeScene es(scene, threads);
  LightSampler lights(scene);
  PhotonMaps maps = trace_photons(es, lights, photons, seed, threads, method);
  RenderOptions ro = small_options(size, gather, k, seed, threads, shadow_rays, spp);
  ro.batch_queries = 4096;  // several passes, so the pass logic is exercised
  SmallRender out;
  FinalGatherRenderer r(es, lights, *maps.global, maps.caustic.get(), ro);
  out.image = r.render(out.stats);
  out.photons = maps.global->size();
  out.has_caustic_map = maps.caustic != nullptr;
  out.caustic_photons = maps.caustic ? maps.caustic->size() : 0;
  return out;
}

// A closed cube whose every face emits Le and reflects diffusely with albedo rho, seen from the
// inside: the radiance everywhere is Le / (1 - rho) (the white furnace).
Scene furnace_scene(float Le, float rho) {
  Scene s;
  s.name = "furnace";
  Material m;
  m.name = "glowing white";
  m.kd = {rho, rho, rho};
  m.emission = {Le, Le, Le};
  auto id = s.add_material(m);
  const float L = 100.0f;
  Vec3 p[8];
  for (int i = 0; i < 8; ++i) p[i] = {(i & 1) ? L : 0.0f, (i & 2) ? L : 0.0f, (i & 4) ? L : 0.0f};
  const int faces[6][4] = {{0, 2, 3, 1}, {4, 5, 7, 6}, {0, 1, 5, 4}, {2, 6, 7, 3}, {0, 4, 6, 2}, {1, 3, 7, 5}};
  const Vec3 centre{L / 2, L / 2, L / 2};
  for (const auto& f : faces) {
    Vec3 a = p[f[0]], b = p[f[1]], c = p[f[2]], d = p[f[3]];
    // Front side (the emitting one) towards the inside.
    if (dot(cross(b - a, c - a), centre - a) < 0) std::swap(b, d);
    s.add_quad(a, b, c, d, id);
  }
  s.camera.position = {30, 40, 45};
  s.camera.direction = normalize(Vec3{1, 0.7f, 0.9f});
  s.camera.up = {0, 1, 0};
  s.camera.vfov_deg = 100;
  return s;
}

bool has_method(const std::string& m) {
  for (const auto& n : method_names())
    if (n == m) return true;
  return false;
}

std::string write_text(const std::string& name, const std::string& text) {
  std::string path = test::tmp_path(name);
  std::ofstream(path) << text;
  return path;
}

}  // namespace

TEST_CASE("render: photon records are 24 bytes and keep power and direction") {
  CHECK(sizeof(PhotonRecord) == 24);
  Rng rng(3, 4, 5);
  for (int i = 0; i < 1000; ++i) {
    Vec3 d = normalize(Vec3{rng.uniform() - 0.5f, rng.uniform() - 0.5f, rng.uniform() - 0.5f});
    Vec3 pw{rng.uniform() * 3, rng.uniform(), rng.uniform() * 0.01f};
    PhotonRecord r;
    r.set_direction(d);
    r.set_power(pw);
    CHECK(dot(r.get_direction(), d) > 1.0f - 1e-6f);
    Vec3 back = r.get_power();
    for (int c = 0; c < 3; ++c) CHECK(std::fabs(back[c] - pw[c]) <= 1e-3f * pw[c] + 1e-7f);
  }
}

TEST_CASE("render: a small Cornell render is deterministic and finite and non-negative for any thread count") {
  Scene scene = cornell_scene();
  SmallRender a = small_render(scene, "bruteforce", 3000, 40, 6, 1);
  SmallRender b = small_render(scene, "bruteforce", 3000, 40, 6, 2);
  CHECK_FALSE(a.has_caustic_map);  // no specular surfaces in the Cornell Box
  CHECK(a.photons >= 3000);
  CHECK(a.stats.queries > 0);
  CHECK(a.stats.index_calls == a.stats.passes);  // one batched call per pass
  CHECK(a.stats.passes > 1);
  REQUIRE(a.image.rgb.size() == 40u * 40u * 3u);
  std::size_t lit = 0;
  for (float v : a.image.rgb) {
    REQUIRE(std::isfinite(v));
    REQUIRE(v >= 0.0f);
    lit += v > 0;
  }
  CHECK(lit > a.image.rgb.size() / 2);
  CHECK(a.image.rgb == b.image.rgb);  // bit for bit, 1 thread vs 2
  SmallRender c = small_render(scene, "bruteforce", 3000, 40, 6, 2, /*seed=*/8);
  CHECK(c.image.rgb != a.image.rgb);  // the seed does matter
}

TEST_CASE("render: energy is conserved in a white furnace where radiance is Le over 1 - rho") {
  const float Le = 1.0f, rho = 0.5f, expect = Le / (1.0f - rho);
  Scene scene = furnace_scene(Le, rho);
  // Photon tracing alone: the power arriving at surfaces is Phi / (1 - rho).
  {
    EmbreeScene es(scene, 2);
    LightSampler lights(scene);
    PhotonTraceOptions po;
    po.photons = 40000;
    PhotonTraceResult t = trace_photons(es, lights, po);
    Vec3 phi = lights.total_power();
    CHECK(phi.x == doctest::Approx(kPi * Le * 6 * 100 * 100).epsilon(1e-4));
    CHECK(t.stored_power.x / phi.x == doctest::Approx(1.0 / (1.0 - rho)).epsilon(0.02));
  }
  // The whole renderer: emission + direct light + final gather over the photon map.
  // Enough light samples that a pixel's noise is a few per cent (area sampling of an emitter
  // that surrounds the point is noisy near the cube's edges).
  SmallRender r = small_render(scene, "bruteforce", 20000, 16, 24, 2, 11, 32, 48, 2);
  double sum = 0, worst = 0;
  for (std::size_t i = 0; i < r.image.pixels(); ++i) {
    double l = luminance(r.image.at(i));
    sum += l;
    worst = std::max(worst, std::fabs(l - expect) / expect);
  }
  double mean = sum / r.image.pixels();

  MESSAGE("furnace: mean radiance " << mean << " (expected " << expect << "), worst pixel off by "
                                    << 100 * worst << "%");
  CHECK(mean == doctest::Approx(expect).epsilon(0.03));
  // Per pixel the estimate is noisy (light samples near the cube's edges), not biased: most pixels
  // are close, none far off.
  std::size_t close = 0;
  for (std::size_t i = 0; i < r.image.pixels(); ++i)
    close += std::fabs(luminance(r.image.at(i)) - expect) / expect < 0.15;
  CHECK(close >= 0.9 * r.image.pixels());
  CHECK(worst < 0.5);
}

TEST_CASE("render: the OpenEXR image round-trips and the PNG preview is written") {
  Image img(37, 23);
  Rng rng(1, 2, 3);
  for (auto& v : img.rgb) v = rng.uniform() * 100.0f;
  img.rgb[5] = 0.0f;
  img.rgb[6] = 65504.0f;  // the largest half
  std::string path = test::tmp_path("roundtrip.exr");
  write_exr(path, img);
  Image back = read_exr(path);
  REQUIRE(back.width == 37);
  REQUIRE(back.height == 23);
  for (std::size_t i = 0; i < img.rgb.size(); ++i)
    REQUIRE(back.rgb[i] == static_cast<float>(Imath::half(img.rgb[i])));  // exactly the halves
  std::string png = test::tmp_path("roundtrip.png");
  Rgb8 tm = tonemap(img, 0.01f);
  write_png(png, tm);
  Rgb8 pback = read_png(png);
  CHECK(pback.width == 37);
  CHECK(pback.px == tm.px);
  CHECK_THROWS_WITH_AS(read_exr(test::tmp_path("no-such.exr")),
                       doctest::Contains("no-such.exr: reading the OpenEXR image failed"), Error);
  CHECK_THROWS_WITH_AS(write_exr("/no/such/dir/x.exr", img), doctest::Contains("/no/such/dir/x.exr"), Error);
}

TEST_CASE("render: brute force and the kd-tree give the same image") {
  Scene scene = cornell_scene();
  SmallRender a = small_render(scene, "bruteforce", 3000, 32, 6, 2);
  SmallRender b = small_render(scene, "kdtree", 3000, 32, 6, 2);
  ImageDiff d = image_diff(b.image, a.image);
  MESSAGE("kdtree vs bruteforce: max abs " << d.max_abs << ", rmse " << d.rmse);
  // Both exact with the same tie rule: the same photons, so the same image (float sums may differ
  // only if the two kernels rounded a distance differently).
  CHECK(d.relative_rmse < 1e-5);
}

TEST_CASE("render: a specular scene builds a caustic map and renders finite") {
  Scene scene = load_scene(std::string(BHCL_SCENES_DIR) + "/cornell-specular.obj");
  CHECK(scene.has_specular());
  SmallRender r = small_render(scene, "bruteforce", 4000, 32, 4, 2);
  CHECK(r.has_caustic_map);
  CHECK(r.caustic_photons > 0);
  CHECK(r.caustic_photons < r.photons);
  CHECK(r.stats.caustic_queries == r.stats.visible_points);
  for (float v : r.image.rgb) REQUIRE((std::isfinite(v) && v >= 0));
  // The glass and mirror blocks are visible and let light through: the image is not black there.
  double sum = 0;
  for (float v : r.image.rgb) sum += v;
  CHECK(sum > 0);
}

TEST_CASE("render: hostile scenes are refused naming the file and line: overflow, escaping mtllib, non-material files, FIFOs") {
  const std::string head = "mtllib ok.mtl\nusemtl l\n";
  write_text("ok.mtl", "newmtl w\nKd 0.5 0.5 0.5\nnewmtl l\nKe 1 1 1\nKd 0 0 0\n");
  write_text("secret.txt", "password hunter2\n");
  write_text("hot.mtl", "newmtl l\nKe 1e30 1e30 1e30\nKd 0 0 0\n");
  struct Case {
    std::string text, expect, never;  // `never`: text the message must not quote
  };
  const std::vector<Case> cases = {
      // Finite coordinates whose cross product, area or normal overflow.
      {head + "v 1e20 0 0\nv 0 1e20 0\nv 0 0 1e20\nf 1 2 3\n", "h1.obj:6: the face's area or normal overflows", ""},
      {head + "v 3e38 0 0\nv -3e38 1 0\nv 0 3e38 0\nf 1 2 3\n", "h2.obj:6: the face's area or normal overflows", ""},
      // Emission times area beyond the float range.
      {"mtllib hot.mtl\nusemtl l\nv 0 0 0\nv 1e5 0 0\nv 0 1e5 0\nf 1 2 3\n", "h3.obj:6: the face's emitted power overflows", ""},
      // A camera whose direction overflows.
      {head + "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\ncamera -3e38 0 0 3e38 0 0 0 1 0 40\n", "h4.obj:7: the camera's direction overflows", ""},
      // Material libraries outside the scene's folder, and a file that is not one.
      {"mtllib /etc/passwd\n", "h5.obj:1: mtllib must name a file inside the scene's folder", ""},
      {"mtllib ../ok.mtl\n", "h6.obj:1: mtllib must name a file inside the scene's folder", ""},
      {"mtllib secret.txt\n", "secret.txt:1: not a material library", "hunter2"},
      {"mtllib secret.txt\n", "not a material library", "password"},
  };
  int i = 0;
  for (const auto& c : cases) {
    const std::string path = write_text("h" + std::to_string(++i) + ".obj", c.text);
    INFO(c.text);
    const std::string msg = test::error_of([&] { load_scene(path); });
    INFO(msg);
    CHECK(msg.find(c.expect) != std::string::npos);
    if (!c.never.empty()) CHECK(msg.find(c.never) == std::string::npos);
    const bool names_file = msg.find(path) != std::string::npos || msg.find("secret.txt") != std::string::npos;
    CHECK(names_file);
  }
  // A FIFO or a directory as the scene is refused before it is opened (an open would wait).
  const std::string fifo = test::tmp_path("scene_fifo.obj");
  std::remove(fifo.c_str());
  REQUIRE(mkfifo(fifo.c_str(), 0600) == 0);
  CHECK_THROWS_WITH_AS(load_scene(fifo), doctest::Contains("is a FIFO"), Error);
  CHECK_THROWS_WITH_AS(load_obj_scene(test::tmp_path("")), doctest::Contains("is a directory"), Error);
}

TEST_CASE("render: bad scene files give errors naming the file and the line") {
  std::string mtl = write_text("ok.mtl", "newmtl w\nKd 0.5 0.5 0.5\nnewmtl l\nKe 1 1 1\nKd 0 0 0\n");
  const std::string head = "mtllib ok.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\n";
  struct Case {
    std::string text, expect;
  };
  std::vector<Case> cases = {
      {head + "usemtl l\nf 1 2 3\nf 1 2 9\n", "bad1.obj:7: face vertex 9 out of range"},
      {head + "usemtl nope\n", "bad2.obj:5: material 'nope' is not defined"},
      {head + "v 1 x 2\n", "bad3.obj:5: bad number 'x'"},
      {head + "frobnicate 1\n", "bad4.obj:5: unknown statement 'frobnicate'"},
      {head + "usemtl w\nf 1 2\n", "bad5.obj:6: a face needs at least 3 vertices"},
      {head + "usemtl w\nf 1 2 3\n", "no emitting surface"},
      {"mtllib missing.mtl\n", "missing.mtl: cannot open a material library"},
      {head + "usemtl l\nf 1 2 3\ncamera 0 0 0 0 0 0 0 1 0 40\n", "bad8.obj:7: camera target equals its position"},
      {head + "usemtl l\nf 1 2 2\n", "bad9.obj:6: the face is degenerate (zero area)"},
  };
  int i = 0;
  for (const auto& c : cases) {
    std::string path = write_text("bad" + std::to_string(++i) + ".obj", c.text);
    INFO(c.text);
    CHECK_THROWS_WITH_AS(load_scene(path), doctest::Contains(c.expect.c_str()), Error);
  }
  std::string badmtl = write_text("badm.mtl", "newmtl w\nKd 1.5 0.5 0.5\n");
  std::string obj = write_text("badm.obj", "mtllib badm.mtl\n");
  CHECK_THROWS_WITH_AS(load_scene(obj), doctest::Contains("badm.mtl:2: reflectance of 'w' must be in [0, 1]"), Error);
  CHECK_THROWS_WITH_AS(load_scene("no-such-scene"), doctest::Contains("scene 'no-such-scene' not found"), Error);
  // A good file loads, with the default camera when it has none.
  std::string good = write_text("good.obj", head + "usemtl l\nf 1 2 3\nusemtl w\nf -3 -1 -2\n");
  Scene s = load_scene(good);
  CHECK(s.triangles.size() == 2);
  CHECK(s.has_light());
}

TEST_CASE("render: bhcl render writes the EXR and the PNG and the stats") {
  std::string exr = test::tmp_path("cli_render.exr"), json = test::tmp_path("cli_render.json");
  std::string out = test::run_bhcl_ok("render --scene cornell --method bruteforce --photons 2000 --gather 4 --k 8 "
                          "--size 24x16 --quiet --out " + exr + " --stats " + json);
  CHECK(out.find("no caustic map built") != std::string::npos);
  Image img = read_exr(exr);
  CHECK(img.width == 24);
  CHECK(img.height == 16);
  CHECK(read_png(test::tmp_path("cli_render.png")).width == 24);
  std::ifstream s(json);
  const nlohmann::json j = nlohmann::json::parse(s);
  INFO(j.dump(2));
  for (const char* key : {"photons", "queries", "query_s", "total_s", "photon_s", "index_build_s", "shade_s"})
    CHECK_MESSAGE(j.at(key).is_number(), key);
  CHECK(j.at("device").is_string());
  CHECK(j.at("method") == "bruteforce");
  CHECK(j.at("k") == 8);
  CHECK(j.at("width") == 24);
  CHECK(j.at("photons_requested") == 2000);
  CHECK(j.at("search").at("k") == 8);
  CHECK(test::run_bhcl("render --out " + exr + " --size 12", &out) == 2);
  CHECK(out.find("--size expects WxH") != std::string::npos);
  CHECK(test::run_bhcl("render --out " + exr + " --scene /no/such.obj", &out) == 1);
  CHECK(out.find("/no/such.obj: cannot open a scene file") != std::string::npos);
}

TEST_CASE("render: --compare with the paper preset sizes B for each A and reports the lists' false negatives and dilation") {
  const std::string base = test::tmp_path("cli_cmp_paper"), exr = base + ".exr", json = base + ".json";
  std::string out;
  // B from the design A of 8 made every A the same build: A had no effect on the image (issue 41).
  const std::string common = "render --scene cornell --photons 20000 --gather 4 --k 20 --size 24x24 --quiet ";
  int rc = test::run_bhcl(common + "--compare --preset paper --compare-A 2,16 --out " + exr + " --stats " + json, &out);
  INFO(out);
  REQUIRE(rc == 0);
  std::ifstream s(json);
  const nlohmann::json j = nlohmann::json::parse(s);
  REQUIRE(j.at("runs").size() == 3);
  const auto& a2 = j.at("runs")[1];
  const auto& a16 = j.at("runs")[2];
  const double lnN = std::log(double(j.at("photons").get<long>()));
  CHECK(a2.at("build").at("B").get<int>() == int(std::ceil(2.0 * 20 / (10 * lnN))) + 1);
  CHECK(a16.at("build").at("B").get<int>() == int(std::ceil(16.0 * 20 / (10 * lnN))) + 1);
  CHECK(a16.at("build").at("B").get<int>() > a2.at("build").at("B").get<int>());
  // The talk's measures of the lists against the exact method's: more candidates, fewer misses.
  const auto& l2 = a2.at("lists_accuracy");
  const auto& l16 = a16.at("lists_accuracy");
  CHECK(l2.at("queries").get<long>() > 100);
  CHECK(l16.at("false_negative_rate").get<double>() < l2.at("false_negative_rate").get<double>());
  CHECK(l16.at("mean_dilation").get<double>() < l2.at("mean_dilation").get<double>());
  CHECK(l16.at("mean_dilation").get<double>() >= 1.0);
  CHECK(out.find("the talk's measures") != std::string::npos);
  CHECK(read_exr(base + "_A2.exr").rgb != read_exr(base + "_A16.exr").rgb);
}

TEST_CASE("render: --compare stops at an A whose image repeats, and --noise-floor and --photon-seed work") {
  const std::string base = test::tmp_path("cli_cmp"), exr = base + ".exr", json = base + ".json";
  std::string out;
  // A = 64 and 128 examine far more than all 2000 photons' worth of candidates at k = 8: their
  // images are bit-identical, so 256 must be skipped.
  const std::string common = "render --scene cornell --photons 2000 --gather 4 --k 8 --size 16x16 --quiet ";
  int rc = test::run_bhcl(common + "--compare --exact bruteforce --compare-A 64,128,256 --noise-floor --out " + exr +
                              " --stats " + json, &out);
  INFO(out);
  REQUIRE(rc == 0);
  std::ifstream s(json);
  const nlohmann::json j = nlohmann::json::parse(s);
  REQUIRE(j.at("runs").size() >= 3);
  if (j.at("runs").size() == 3) {  // skipped 256: 64 and 128 must then be identical
    CHECK(out.find("larger A skipped") != std::string::npos);
    CHECK(read_exr(base + "_A64.exr").rgb == read_exr(base + "_A128.exr").rgb);
  } else {
    CHECK(read_exr(base + "_A64.exr").rgb != read_exr(base + "_A128.exr").rgb);
  }
  REQUIRE(j.at("noise_floor").size() == 2);
  for (const auto& n : j.at("noise_floor")) CHECK(n.at("rmse").get<double>() > 0);  // other seeds differ
  CHECK(out.find("noise floor: exact, photon seed") != std::string::npos);
  // --photon-seed changes the photons only; the same pair of seeds gives the same image.
  auto render = [&](const std::string& seeds, const std::string& name) {
    std::string o;
    REQUIRE(test::run_bhcl(common + "--method bruteforce " + seeds + " --out " + test::tmp_path(name), &o) == 0);
    return read_exr(test::tmp_path(name)).rgb;
  };
  auto a = render("--seed 3 --photon-seed 4", "seeds_a.exr");
  CHECK(a == render("--seed 3 --photon-seed 4", "seeds_b.exr"));
  CHECK(a != render("--seed 3 --photon-seed 5", "seeds_c.exr"));
  CHECK(a != render("--seed 2 --photon-seed 4", "seeds_d.exr"));
  CHECK(test::run_bhcl(common + "--noise-floor --out " + exr, &out) == 2);  // only with --compare
}

TEST_CASE("render: the comparison sheet: exact zero is black, the automatic scale is a percentile, labels are drawn") {
  Image ref(10, 10), a(10, 10);
  for (std::size_t i = 0; i < ref.pixels(); ++i) {
    ref.set(i, Vec3{1, 1, 1});
    // Pixel i off by i per cent (pixel 0 exact).
    a.set(i, Vec3{1, 1, 1} * (1.0f + 0.01f * static_cast<float>(i)));
  }
  Rgb8 fc = false_colour_difference(a, ref, 0.5f);
  CHECK(fc.px[0] == 0);
  CHECK(fc.px[1] == 0);
  CHECK(fc.px[2] == 0);
  CHECK(fc.px[3] + fc.px[4] + fc.px[5] > 0);  // 1 %: small but not black
  CHECK(relative_error_percentile({&a}, ref, 0.99f) == doctest::Approx(0.99f).epsilon(1e-4));
  CHECK(relative_error_percentile({&a}, ref, 0.5f) == doctest::Approx(0.50f).epsilon(1e-4));
  CHECK(relative_error_percentile({}, ref, 0.99f) == 0.0f);
  TextPainter text(12);
  MESSAGE("text painter: " << (text.ok() ? "ok" : text.why()));
  Rgb8 tile(120, 40, 0);
  Rgb8 sheet = labelled_sheet({{Panel{tile, {"blockhash A=4", "RMSE 0.001"}}}}, 4, text);
  CHECK(sheet.width == 128);
  if (text.ok()) {
    CHECK(sheet.height == 40 + 2 * text.line_height() + 2 + 8);
    // The band above the tile carries white-ish glyph pixels; the grey background alone is 40.
    int bright = 0;
    for (int y = 4; y < 4 + 2 * text.line_height(); ++y)
      for (int x = 4; x < 124; ++x) bright += sheet.px[(static_cast<std::size_t>(y) * sheet.width + x) * 3] > 200;
    CHECK(bright > 30);
    CHECK(text.width("RMSE") > 0);
  } else {
    CHECK(sheet.height == 48);
  }
}

TEST_CASE("render: block errors against a reference leave out the emitter's blocks and give the bias") {
  Image ref(8, 8), a(8, 8);
  for (std::size_t i = 0; i < ref.pixels(); ++i) {
    ref.set(i, Vec3{1, 1, 1});
    // Per pixel +-20 % noise that cancels within each 2x2 block, and a uniform +1 % bias.
    const float noise = ((i % 8) + (i / 8)) % 2 ? 0.2f : -0.2f;
    a.set(i, Vec3{1, 1, 1} * (1.01f + noise));
  }
  ref.set(0, Vec3{50, 50, 50});  // the emitter, seen in the top-left block only
  a.set(0, Vec3{10, 10, 10});
  BlockError e = block_error(a, ref, 2);
  CHECK(e.blocks == 15);
  CHECK(e.blocks_left_out == 1);
  CHECK(e.mean_bias == doctest::Approx(0.01).epsilon(1e-3));
  CHECK(e.relative_rmse == doctest::Approx(0.01).epsilon(1e-3));  // the noise averaged away
  CHECK(image_diff(a, ref).relative_rmse > 0.1);                   // per pixel it is not
  CHECK_THROWS_AS(block_error(a, Image(4, 4), 2), Error);
  CHECK_THROWS_AS(block_error(a, ref, 0), Error);
}

TEST_CASE("render: the automatic exposure is not pulled down by pixels that see the light") {
  Image img(20, 10);
  for (std::size_t i = 0; i < img.pixels(); ++i) img.set(i, Vec3{0.5f, 0.5f, 0.5f} * (0.5f + 0.005f * (i % 100)));
  const float walls = auto_exposure(img);
  for (std::size_t i = 0; i < 10; ++i) img.set(i, Vec3{40, 40, 40});  // 5 % of the pixels: the light
  CHECK(auto_exposure(img) == doctest::Approx(walls).epsilon(0.05));
  CHECK(walls == doctest::Approx(1.0f / (0.5f * (0.5f + 0.005f * 98))).epsilon(0.03));
  CHECK(auto_exposure(Image(4, 4)) == 1.0f);  // black
}

// ---- Radiance through refracting surfaces -------------------------------------------------------
// Radiance divided by n^2 is what is conserved along a ray (and, without absorption, across a
// smooth interface up to the Fresnel factor), so a surface inside glass seen from the air looks
// (1 / ior)^2 as bright as it is inside. A closed glass object cancels the two crossings; these
// scenes have a single interface, where a missing factor shows as a 2.25x error.
namespace {

Image glass_render(const Scene& scene, std::size_t photons, int size, int gather, int shadow_rays,
                   int spp, int k, float caustic_radius, std::uint64_t seed = 5, int max_specular_depth = 0) {
  EmbreeScene es(scene, 2);
  LightSampler lights(scene);
  PhotonMaps maps = trace_photons(es, lights, photons, seed, 2, "bruteforce");
  RenderOptions ro = small_options(size, gather, k, seed, 2, shadow_rays, spp);
  ro.caustic_k = k;
  ro.caustic_radius = caustic_radius;
  if (max_specular_depth > 0) ro.max_specular_depth = max_specular_depth;
  RenderStats stats;
  FinalGatherRenderer r(es, lights, *maps.global, maps.caustic.get(), ro);
  return r.render(stats);
}

Image path_traced(const Scene& scene, int size, int spp, int threads, PathTraceStats& st) {
  EmbreeScene es(scene, threads);
  LightSampler lights(scene);
  PathTraceOptions po;
  po.width = po.height = size;
  po.spp = spp;
  po.threads = threads;
  return path_trace(es, lights, po, st);
}

Material glass_material(float ior) {
  Material g;
  g.name = "glass";
  g.type = MaterialType::Glass;
  g.ks = {1, 1, 1};
  g.ior = ior;
  return g;
}

}  // namespace

TEST_CASE("render: an emitter inside glass seen through one interface has radiance T Le / ior^2") {
  // A black emitter 10 mm under the flat top of a glass slab (no other face), seen from above
  // at near-normal incidence (10 degree field of view): a refracted camera ray carries
  // (1 - F) Le / ior^2; a Fresnel-reflected one goes up and escapes (the only diffuse panel, there
  // so that photons have somewhere to land, is off to the side, out of the reflected cone).
  const float Le = 1.0f, ior = 1.5f;
  Scene s;
  s.name = "slab";
  const Material glass = glass_material(ior);
  Material light;
  light.name = "light";
  light.kd = {0, 0, 0};
  light.emission = {Le, Le, Le};
  Material white;
  white.name = "white";
  white.kd = {0.5f, 0.5f, 0.5f};
  auto g = s.add_material(glass), l = s.add_material(light), w = s.add_material(white);
  // Counter-clockwise seen from +y: front faces up (the glass's outside is the air above).
  s.add_quad({-50, 0, -50}, {-50, 0, 50}, {50, 0, 50}, {50, 0, -50}, g);
  s.add_quad({-50, -10, -50}, {-50, -10, 50}, {50, -10, 50}, {50, -10, -50}, l);
  s.add_quad({30, 100, -50}, {80, 100, -50}, {80, 100, 50}, {30, 100, 50}, w);  // faces down
  s.camera.position = {0, 20, 0};
  s.camera.direction = {0, -1, 0};
  s.camera.up = {0, 0, 1};
  s.camera.vfov_deg = 10;
  Image img = glass_render(s, 2000, 16, 0, 1, 8, 8, 5.0f);
  const double T = 1.0 - fresnel_dielectric(1.0f, 1.0f / ior);  // 0.96 at normal incidence
  const double expect = T * Le / (ior * ior);
  const double mean = mean_luminance(img);
  MESSAGE("emitter under one interface: mean radiance " << mean << ", expected " << expect);
  // 2048 camera samples, each T-likely to carry Le / ior^2: about 0.5 % noise on the mean.
  CHECK(mean == doctest::Approx(expect).epsilon(0.03));
}

TEST_CASE("render: a white furnace half filled with glass keeps radiance / n^2 uniform") {
  // A closed cube whose faces reflect diffusely (albedo rho) and emit; a horizontal glass
  // interface at half height fills the lower half with glass (ior n). Walls in the glass emit
  // n^2 Le, walls in the air Le: the equilibrium is radiance Le / (1 - rho) everywhere in the air
  // and n^2 Le / (1 - rho) everywhere in the glass (radiance / n^2 uniform, as in thermal
  // equilibrium). The camera, in the air, looks down through the interface at the glass half:
  // every pixel should read Le / (1 - rho). Without the n^2 factors the glass half comes out
  // brighter by up to n^2.
  const float Le = 1.0f, rho = 0.5f, n = 1.5f, expect = Le / (1.0f - rho), L = 100.0f, H = 50.0f;
  Scene s;
  s.name = "glass furnace";
  Material air_wall, glass_wall, glass;
  air_wall.name = "air wall";
  air_wall.kd = {rho, rho, rho};
  air_wall.emission = {Le, Le, Le};
  glass_wall = air_wall;
  glass_wall.name = "glass wall";
  glass_wall.emission = air_wall.emission * (n * n);
  glass.name = "glass";
  glass.type = MaterialType::Glass;
  glass.ks = {1, 1, 1};
  glass.ior = n;
  auto ma = s.add_material(air_wall), mg = s.add_material(glass_wall), mi = s.add_material(glass);
  const Vec3 centre{L / 2, L / 2, L / 2};
  // A quad facing the cube's centre (the emitting side is the front).
  auto inward = [&](Vec3 a, Vec3 b, Vec3 c, Vec3 d, std::uint32_t m) {
    Vec3 mid = (a + b + c + d) * 0.25f;
    Vec3 to_centre{0, 0, 0};
    // Side walls: towards the vertical axis; floor and ceiling: towards the centre.
    to_centre = (std::fabs(mid.y) < 1e-3f || std::fabs(mid.y - L) < 1e-3f) ? centre - mid
                                                                             : Vec3{L / 2 - mid.x, 0, L / 2 - mid.z};
    if (dot(cross(b - a, c - a), to_centre) < 0) std::swap(b, d);
    s.add_quad(a, b, c, d, m);
  };
  inward({0, 0, 0}, {L, 0, 0}, {L, 0, L}, {0, 0, L}, mg);  // floor, in the glass
  inward({0, L, 0}, {L, L, 0}, {L, L, L}, {0, L, L}, ma);  // ceiling, in the air
  for (int half = 0; half < 2; ++half) {
    const float y0 = half ? H : 0, y1 = half ? L : H;
    const auto m = half ? ma : mg;
    inward({0, y0, 0}, {L, y0, 0}, {L, y1, 0}, {0, y1, 0}, m);
    inward({0, y0, L}, {L, y0, L}, {L, y1, L}, {0, y1, L}, m);
    inward({0, y0, 0}, {0, y0, L}, {0, y1, L}, {0, y1, 0}, m);
    inward({L, y0, 0}, {L, y0, L}, {L, y1, L}, {L, y1, 0}, m);
  }
  // The interface: front (the glass's outside) up, towards the air.
  s.add_quad({0, H, 0}, {0, H, L}, {L, H, L}, {L, H, 0}, mi);
  s.camera.position = {L / 2, 95, L / 2};
  s.camera.direction = {0, -1, 0};
  s.camera.up = {0, 0, 1};
  s.camera.vfov_deg = 90;
  Image img = glass_render(s, 20000, 16, 24, 48, 2, 32, 12.0f, 11);
  const double mean = mean_luminance(img);
  // The centre quarter of the image sees only the glass half's floor, through the interface.
  double centre_sum = 0;
  int centre_n = 0;
  for (int y = 4; y < 12; ++y)
    for (int x = 4; x < 12; ++x, ++centre_n) centre_sum += luminance(img.at(static_cast<std::size_t>(y) * 16 + x));
  const double centre_mean = centre_sum / centre_n;
  MESSAGE("glass furnace: mean radiance " << mean << ", floor through the interface " << centre_mean
                                          << " (expected " << expect << " everywhere)");
  CHECK(mean == doctest::Approx(expect).epsilon(0.05));
  CHECK(centre_mean == doctest::Approx(expect).epsilon(0.06));
}

// A box of glass faces (outward fronts) from lo to hi; the bottom face (y = lo.y) only if asked.
void add_glass_box(Scene& s, Vec3 lo, Vec3 hi, std::uint32_t m, bool bottom) {
  Vec3 p[8];
  for (int i = 0; i < 8; ++i) p[i] = {(i & 1) ? hi.x : lo.x, (i & 2) ? hi.y : lo.y, (i & 4) ? hi.z : lo.z};
  const int faces[6][4] = {{0, 1, 5, 4}, {2, 6, 7, 3}, {0, 4, 6, 2}, {1, 3, 7, 5}, {0, 2, 3, 1}, {4, 5, 7, 6}};
  const Vec3 centre = (lo + hi) * 0.5f;
  for (int f = 0; f < 6; ++f) {
    if (f == 0 && !bottom) continue;
    Vec3 a = p[faces[f][0]], b = p[faces[f][1]], c = p[faces[f][2]], d = p[faces[f][3]];
    if (dot(cross(b - a, c - a), a - centre) < 0) std::swap(b, d);  // front outwards
    s.add_quad(a, b, c, d, m);
  }
}

TEST_CASE("render: camera chains trapped by total internal reflection are followed as deep as the path tracer's") {
  // A glass light pipe (4 x 4 x 70, closed) in the white furnace, its end face seen at 50 degrees
  // from its axis through a 10 degree field of view: a refracted camera ray runs down the pipe at
  // 31 degrees to the axis, reflected totally by the side faces about 10 times before the far end.
  // In the furnace every chain that reaches a wall sees Le / (1 - rho) (the n^2 factors of the two
  // crossings cancel), so every pixel should. The renderer used to end a chain after 8 specular
  // vertices (the path tracer after 64): the pipe came out black but for its Fresnel reflection,
  // as the shipped glass block's right face came out 3x too dark (issue 24).
  const float Le = 1.0f, rho = 0.5f, expect = Le / (1.0f - rho);
  Scene s = furnace_scene(Le, rho);
  s.name = "light pipe";
  add_glass_box(s, {48, 48, 15}, {52, 52, 85}, s.add_material(glass_material(1.5f)), true);
  const float a = 50.0f * kPi / 180.0f;
  s.camera.position = {50 + 10 * std::sin(a), 50, 15 - 10 * std::cos(a)};
  s.camera.direction = {-std::sin(a), 0, std::cos(a)};
  s.camera.up = {0, 1, 0};
  s.camera.vfov_deg = 10;
  const Image deep = glass_render(s, 20000, 8, 24, 16, 4, 32, 12.0f, 11);
  const Image cut = glass_render(s, 20000, 8, 24, 16, 4, 32, 12.0f, 11, 8);
  const double mean = mean_luminance(deep), mean_cut = mean_luminance(cut);
  MESSAGE("light pipe: mean radiance " << mean << " (expected " << expect << "); chains cut at 8 specular vertices: "
                                       << mean_cut);
  CHECK(RenderOptions{}.max_specular_depth >= PathTraceOptions{}.max_depth);
  CHECK(mean == doctest::Approx(expect).epsilon(0.06));
  CHECK(mean_cut < 0.5 * expect);  // the scene does need the deep chains
}

TEST_CASE("render: the path tracer's window traces only its pixels, each as the whole image has it") {
  // bhcl pathtrace --window refines a reference where its paths are rare (issue 24).
  Scene s = furnace_scene(1.0f, 0.5f);
  EmbreeScene es(s, 2);
  LightSampler lights(s);
  PathTraceOptions po;
  po.width = po.height = 12;
  po.spp = 4;
  po.threads = 2;
  PathTraceStats st, sw;
  const Image full = path_trace(es, lights, po, st);
  po.window_x0 = 3;
  po.window_y0 = 5;
  po.window_x1 = 7;
  po.window_y1 = 6;
  const Image win = path_trace(es, lights, po, sw);
  CHECK(sw.paths == 4 * 1 * 4);
  std::size_t same = 0, zero = 0;
  for (int y = 0; y < 12; ++y)
    for (int x = 0; x < 12; ++x) {
      const std::size_t i = static_cast<std::size_t>(y) * 12 + x;
      const bool in = x >= 3 && x < 7 && y == 5;
      const Vec3 a = win.at(i), b = full.at(i);
      if (in) same += a.x == b.x && a.y == b.y && a.z == b.z;
      else zero += a.x == 0 && a.y == 0 && a.z == 0;
    }
  CHECK(same == 4);
  CHECK(zero == 140);
  po.window_x1 = 13;
  CHECK_THROWS_AS(path_trace(es, lights, po, sw), Error);
}

TEST_CASE("render: photons and queries inside glass are kept apart from those outside it") {
  // A glass block open at the bottom stands on a lit floor (the shipped specular scene's glass
  // block): the floor under it is lit through the glass, the floor beside it directly. Photons
  // on the floor inside are flagged and keyed away by medium_key, so a disc at the floor just
  // inside the wall holds only photons from inside, and one just outside only photons from outside.
  Scene s;
  s.name = "glass on a floor";
  Material white;
  white.name = "white";
  white.kd = {0.5f, 0.5f, 0.5f};
  Material light;
  light.name = "light";
  light.kd = {0, 0, 0};
  light.emission = {10, 10, 10};
  auto w = s.add_material(white), l = s.add_material(light), g = s.add_material(glass_material(1.5f));
  s.add_quad({-100, 0, -100}, {-100, 0, 100}, {100, 0, 100}, {100, 0, -100}, w);  // faces up
  s.add_quad({-60, 100, -60}, {60, 100, -60}, {60, 100, 60}, {-60, 100, 60}, l);   // faces down
  add_glass_box(s, {-20, 0, -20}, {20, 30, 20}, g, false);
  s.camera.position = {0, 60, -150};
  s.camera.direction = normalize(Vec3{0, -0.4f, 1});
  EmbreeScene es(s, 2);
  LightSampler lights(s);
  CHECK(!es.inside_glass({0, 50, 0}));
  CHECK(es.inside_glass({0, 1, 0}));
  CHECK(!es.inside_glass({30, 1, 0}));
  PhotonTraceOptions po;
  po.photons = 30000;
  po.threads = 2;
  PhotonMaps maps = build_photon_maps(es, lights, po);
  const float sep = medium_separation(s.diagonal());
  std::size_t inside = 0, misplaced = 0;
  for (const PhotonRecord& r : maps.global->records()) {
    const bool flagged = (r.flags & PhotonRecord::kInGlass) != 0;
    Vec3 x = r.get_position();
    if (flagged) x.x -= sep;
    const bool under = std::fabs(x.x) < 20 && std::fabs(x.z) < 20 && x.y < 1e-3f;
    inside += flagged;
    misplaced += flagged != under;
  }
  MESSAGE(inside << " of " << maps.global->size() << " photons inside the glass, " << misplaced << " misplaced");
  CHECK(inside > 1000);
  CHECK(misplaced == 0);
  maps.global->build_index("bruteforce", test::runtime());
  SearchParams sp = test::knn_params(50);
  // 1 mm inside and outside the wall at x = 20, keyed as the renderer keys them.
  const Vec3 in = medium_key({19, 0, 0}, true, sep), out = medium_key({21, 0, 0}, false, sep);
  const float q[6] = {in.x, in.y, in.z, out.x, out.y, out.z};
  KnnResult res;
  maps.global->query(q, 2, sp, res);
  for (std::size_t row = 0; row < 2; ++row) {
    REQUIRE(res.counts[row] == sp.k);
    std::size_t wrong = 0;
    for (int j = 0; j < res.counts[row]; ++j) {
      const bool flagged = (maps.global->records()[res.id(row, j)].flags & PhotonRecord::kInGlass) != 0;
      wrong += flagged != (row == 0);
    }
    CHECK(wrong == 0);
  }
}

// ---- Density estimators (the talk's future work) and the traced-once comparison ----------------

TEST_CASE("render: density estimators: filter integrals, and each estimator recovers r_k of a uniform disc") {
  // Each filter's weights integrate to filter_norm() over the unit disc (midpoint rule in r).
  for (DensityFilter f : {DensityFilter::Box, DensityFilter::Cone, DensityFilter::Epanechnikov}) {
    double integral = 0;
    const int steps = 20000;
    for (int i = 0; i < steps; ++i) {
      const double r = (i + 0.5) / steps;
      integral += filter_weight(f, static_cast<float>(r * r), 1.0f, 1.0f) * 2 * r / steps;  // 2 pi r dr / pi
    }
    CHECK_MESSAGE(integral == doctest::Approx(filter_norm(f)).epsilon(1e-4), density_filter_name(f));
  }
  // k photons of a uniform density in the plane, the k nearest of a point: every estimator's
  // radius averages to r_k (kth exactly; mean and var within a few per cent over many draws).
  const int k = 50;
  Rng rng(5, 6, 7);
  double sum[3] = {0, 0, 0};
  const int trials = 400;
  for (int t = 0; t < trials; ++t) {
    std::vector<float> d2(4 * k);
    for (auto& v : d2) v = rng.uniform() * 4.0f;  // squared radii uniform: uniform density in a disc of r = 2
    std::sort(d2.begin(), d2.end());
    const float rk2 = d2[k - 1];
    for (int e = 0; e < 3; ++e)
      sum[e] += std::sqrt(disc_radius2(static_cast<RadiusEstimator>(e), d2.data(), k, k, INFINITY) / rk2);
  }
  CHECK(sum[0] / trials == doctest::Approx(1.0));
  CHECK(sum[1] / trials == doctest::Approx(1.0).epsilon(0.02));
  CHECK(sum[2] / trials == doctest::Approx(1.0).epsilon(0.05));
  // Fewer than k inside the maximum radius: the disc is the maximum radius, whatever the estimator.
  const float few[3] = {0.01f, 0.04f, 0.09f};
  for (int e = 0; e < 3; ++e) CHECK(disc_radius2(static_cast<RadiusEstimator>(e), few, 3, 8, 2.0f) == 4.0f);
  CHECK(disc_radius2(RadiusEstimator::Mean, few, 0, 8, INFINITY) == 0.0f);
  const float same[3] = {0, 0, 0};  // all on the query point: no disc
  for (int e = 0; e < 3; ++e) CHECK(disc_radius2(static_cast<RadiusEstimator>(e), same, 3, 3, INFINITY) == 0.0f);
  RadiusEstimator re;
  DensityFilter df;
  CHECK(parse_radius_estimator("var", re));
  CHECK(re == RadiusEstimator::Variance);
  CHECK_FALSE(parse_radius_estimator("median", re));
  CHECK(parse_density_filter("epanechnikov", df));
  CHECK_FALSE(parse_density_filter("gauss", df));
}

TEST_CASE("render: every density estimator gives the analytic radiance of a uniformly lit plane") {
  // Photons of equal power spread uniformly on a plane, arriving from above: irradiance
  // E = density x power, radiance kd E / pi, for every estimator and filter alike.
  const std::size_t N = 40000;
  const float side = 100.0f, power = 1.0f;
  Rng rng(9, 9, 9);
  std::vector<PhotonRecord> recs(N);
  for (auto& r : recs) {
    r.position[0] = rng.uniform() * side;
    r.position[1] = 0;
    r.position[2] = rng.uniform() * side;
    r.set_power({power, power, power});
    r.set_direction({0, 1, 0});
    r.flags = 0;
  }
  PhotonMap map("plane", recs, 1.0f);
  map.build_index("bruteforce", test::runtime());
  std::vector<float> q;
  for (int i = 0; i < 64; ++i) q.insert(q.end(), {25 + rng.uniform() * 50, 0, 25 + rng.uniform() * 50});
  SearchParams sp = test::knn_params(100);
  KnnResult res;
  map.query(q.data(), 64, sp, res);
  const Vec3 kd{0.5f, 0.5f, 0.5f};
  const double expect = 0.5 / kPi * (N / (side * side)) * power;
  for (RadiusEstimator e : {RadiusEstimator::Kth, RadiusEstimator::Mean, RadiusEstimator::Variance})
    for (DensityFilter f : {DensityFilter::Box, DensityFilter::Cone, DensityFilter::Epanechnikov}) {
      double sum = 0;
      for (std::size_t i = 0; i < 64; ++i) sum += map.radiance(res, i, {0, 1, 0}, kd, INFINITY, {e, f}).x;
      CHECK_MESSAGE(sum / 64 == doctest::Approx(expect).epsilon(0.06), estimator_name({e, f}));
      // Photons from behind the surface add nothing.
      CHECK(map.radiance(res, 0, {0, -1, 0}, kd, INFINITY, {e, f}).x == 0.0f);
    }
}

TEST_CASE("render: rays traced once and shaded per estimator equal a render per estimator, bit for bit") {
  for (const char* scene_name : {"cornell", "cornell-specular"}) {
    Scene scene = load_scene(scene_name);
    EmbreeScene es(scene, 2);
    LightSampler lights(scene);
    PhotonMaps maps = trace_photons(es, lights, 4000, PhotonTraceOptions{}.seed, 2, "bruteforce");
    RenderOptions ro;
    ro.width = 24;
    ro.height = 20;
    ro.gather = 4;
    ro.search.k = 12;
    ro.threads = 2;
    ro.batch_queries = 700;  // several passes
    const std::vector<DensityEstimator> ests = {{RadiusEstimator::Kth, DensityFilter::Cone},
                                                {RadiusEstimator::Mean, DensityFilter::Box},
                                                {RadiusEstimator::Variance, DensityFilter::Epanechnikov}};
    FinalGatherRenderer tracer(es, lights, *maps.global, maps.caustic.get(), ro);
    RenderStats ts;
    TracedFrame frame = tracer.trace(ts);
    CHECK(frame.passes.size() > 1);
    CHECK(frame.bytes() > 0);
    CHECK(ts.queries == 0);  // tracing asks the index nothing
    RenderStats ss;
    std::vector<Image> shaded = tracer.shade(frame, ests, ss);
    REQUIRE(shaded.size() == 3);
    CHECK(ss.index_calls == frame.passes.size() * (maps.caustic ? 2 : 1));  // once per pass, not per estimator
    for (std::size_t e = 0; e < ests.size(); ++e) {
      RenderOptions r1 = ro;
      r1.estimator = ests[e];
      RenderStats rs;
      Image img = FinalGatherRenderer(es, lights, *maps.global, maps.caustic.get(), r1).render(rs);
      CHECK_MESSAGE(img.rgb == shaded[e].rgb, scene_name << " " << estimator_name(ests[e]));
    }
    CHECK(shaded[0].rgb != shaded[1].rgb);  // the estimators do differ
    // A frame traced with other settings is refused.
    RenderOptions other = ro;
    other.seed = 99;
    CHECK_THROWS_WITH_AS(FinalGatherRenderer(es, lights, *maps.global, maps.caustic.get(), other).shade(frame, ests, ss),
                         doctest::Contains("traced frame was made with another scene"), Error);
  }
}

TEST_CASE("render: bhcl render --compare with several estimators, and their misuse") {
  const std::string base = test::tmp_path("cli_est"), exr = base + ".exr", json = base + ".json";
  const std::string common = "render --scene cornell --photons 2000 --gather 4 --k 8 --size 16x16 --quiet ";
  std::string out;
  // A reference image of the same size (a path-traced one), for the estimators' own errors.
  const std::string ref = test::tmp_path("cli_est_ref.exr");
  REQUIRE(test::run_bhcl("pathtrace --scene cornell --size 16x16 --spp 16 --quiet --out " + ref, &out) == 0);
  int rc = test::run_bhcl(common + "--compare --exact bruteforce --compare-A 1,2 --estimator kth,mean --filter "
                                   "cone,box --reference " + ref + " --reference-block 4 --out " + exr +
                              " --stats " + json, &out);
  INFO(out);
  REQUIRE(rc == 0);
  CHECK(out.find("traced once") != std::string::npos);
  CHECK(out.find("estimator mean/box") != std::string::npos);
  CHECK(out.find("against the reference") != std::string::npos);
  std::ifstream s(json);
  const nlohmann::json j = nlohmann::json::parse(s);
  REQUIRE(j.at("estimators").size() == 4);
  for (const auto& e : j.at("estimators")) {
    CHECK(e.at("runs").size() == 3);
    CHECK(e.at("vs_reference").at("block") == 4);
    CHECK(e.at("vs_reference").at("relative_rmse").get<double>() > 0);
  }
  CHECK(read_exr(exr).width == 16);                          // --out: the first estimator's exact render
  CHECK(read_exr(base + "_mean-box_A2.exr").width == 16);    // the others carry the estimator
  CHECK(read_png(base + "_kth-box_compare.png").width > 16);
  // Misuse.
  CHECK(test::run_bhcl(common + "--method bruteforce --estimator kth,mean --out " + exr, &out) == 2);
  CHECK(out.find("--estimator takes a list only with --compare") != std::string::npos);
  CHECK(test::run_bhcl(common + "--method bruteforce --estimator median --out " + exr, &out) == 2);
  CHECK(out.find("unknown radius estimator 'median'") != std::string::npos);
  CHECK(test::run_bhcl(common + "--method bruteforce --filter gauss --out " + exr, &out) == 2);
  CHECK(test::run_bhcl(common + "--compare --estimator kth,kth --out " + exr, &out) == 2);
  CHECK(out.find("listed twice") != std::string::npos);
  CHECK(test::run_bhcl(common + "--method bruteforce --reference " + ref + " --out " + exr, &out) == 2);
  const std::string small = test::tmp_path("cli_est_small.exr");
  REQUIRE(test::run_bhcl("pathtrace --scene cornell --size 8x8 --spp 1 --quiet --out " + small, &out) == 0);
  CHECK(test::run_bhcl(common + "--compare --exact bruteforce --compare-A 1 --reference " + small + " --out " + exr,
                       &out) == 2);
  CHECK(out.find("is 8x8, the render 16x16") != std::string::npos);
  CHECK(test::run_bhcl(common + "--compare --compare-A 1 --reference " + exr + " --out " + exr, &out) == 2);
}

TEST_CASE("render: the path tracer: a white furnace converges to Le over 1 - rho, and Cornell agrees with photon mapping") {
  {
    const float Le = 1.0f, rho = 0.5f;
    Scene scene = furnace_scene(Le, rho);
    PathTraceStats st;
    Image a = path_traced(scene, 16, 256, 2, st);
    MESSAGE("path-traced furnace: mean " << mean_luminance(a) << " (expected 2)");
    CHECK(mean_luminance(a) == doctest::Approx(Le / (1 - rho)).epsilon(0.02));
    CHECK(st.paths == 16u * 16u * 256u);
    CHECK(path_traced(scene, 16, 256, 1, st).rgb == a.rgb);  // independent of threads
  }
  // The diffuse Cornell Box: the photon map's render (exact kNN) and the path tracer agree on the
  // mean radiance within a few per cent (both noisy at this size).
  Scene scene = cornell_scene();
  SmallRender pm = small_render(scene, has_method("kdtree") ? "kdtree" : "bruteforce", 30000, 32, 32, 2, 3, 50, 4, 4);
  PathTraceStats st;
  Image pt = path_traced(scene, 32, 512, 2, st);
  MESSAGE("Cornell 32x32: path tracer mean " << mean_luminance(pt) << ", photon map " << mean_luminance(pm.image));
  CHECK(mean_luminance(pm.image) == doctest::Approx(mean_luminance(pt)).epsilon(0.03));
  std::string out;
  CHECK(test::run_bhcl("pathtrace --out " + test::tmp_path("pt.exr") + " --size 0x4", &out) == 2);
  CHECK(test::run_bhcl("pathtrace --out " + test::tmp_path("pt.exr") + " --spp 0", &out) == 2);
  CHECK(test::run_bhcl("pathtrace --out " + test::tmp_path("pt.exr") + " --scene /no/such.obj", &out) == 1);
  // --window / --base: the window's pixels traced, the others the base image's.
  const std::string base = test::tmp_path("pt_base.exr"), win = test::tmp_path("pt_win.exr");
  REQUIRE(test::run_bhcl("pathtrace --scene cornell --size 8x8 --spp 2 --quiet --out " + base, &out) == 0);
  REQUIRE(test::run_bhcl("pathtrace --scene cornell --size 8x8 --spp 8 --window 2,2,4,3 --base " + base +
                             " --quiet --out " + win, &out) == 0);
  const Image b = read_exr(base), w = read_exr(win);
  std::size_t kept = 0, changed = 0;
  for (int y = 0; y < 8; ++y)
    for (int x = 0; x < 8; ++x) {
      const std::size_t i = static_cast<std::size_t>(y) * 8 + x;
      const bool same = b.at(i).x == w.at(i).x && b.at(i).y == w.at(i).y && b.at(i).z == w.at(i).z;
      if (x >= 2 && x < 4 && y == 2) changed += !same;
      else kept += same;
    }
  CHECK(kept == 62);
  CHECK(changed == 2);
  CHECK(test::run_bhcl("pathtrace --size 8x8 --window 2,2,9,3 --out " + win, &out) == 2);
  CHECK(out.find("--window") != std::string::npos);
  CHECK(test::run_bhcl("pathtrace --size 8x8 --base " + base + " --out " + win, &out) == 2);
  CHECK(test::run_bhcl("pathtrace --size 4x4 --window 0,0,2,2 --base " + base + " --out " + win, &out) == 2);
  CHECK(out.find("is 8x8") != std::string::npos);
}

TEST_CASE("render: progressive photon mapping: the radius sequence, one pass equals the plain render") {
  const double a = 2.0 / 3.0;
  CHECK(ppm_radius_scale2(1, a) == 1.0);
  CHECK(ppm_radius_scale2(2, a) == doctest::Approx((1 + a) / 2));
  // r_{i+1}^2 / r_i^2 = (i + alpha) / (i + 1), and s_i ~ C i^(alpha - 1) as i grows.
  for (int i = 1; i < 50; ++i)
    CHECK(ppm_radius_scale2(i + 1, a) / ppm_radius_scale2(i, a) == doctest::Approx((i + a) / (i + 1)));
  CHECK(ppm_radius_scale2(4000, a) / ppm_radius_scale2(1000, a) == doctest::Approx(std::pow(4.0, a - 1)).epsilon(0.01));
  CHECK_THROWS_AS(ppm_radius_scale2(0, a), Error);
  CHECK_THROWS_AS(ppm_radius_scale2(2, 1.0), Error);
  CHECK(ppm_pass_seed(7, 1) == 7);
  CHECK(ppm_pass_seed(7, 2) != ppm_pass_seed(7, 3));
  CHECK(ppm_pass_seed(7, 2) != ppm_pass_seed(8, 2));

  // One progressive pass is the plain render of the same seeds, bit for bit.
  Scene scene = cornell_scene();
  const std::string m = has_method("kdtree") ? "kdtree" : "bruteforce";
  SmallRender plain = small_render(scene, m, 3000, 16, 4, 2, 7, 16);
  EmbreeScene es(scene, 2);
  LightSampler lights(scene);
  RenderOptions ro = small_options(16, 4, 16, 7, 2);
  ro.batch_queries = 4096;
  ProgressiveOptions po;
  po.passes = 1;
  po.method = m;
  po.runtime = test::runtime();
  po.photons.photons = 3000;
  po.photons.seed = 7;
  po.photons.threads = 2;
  ProgressiveResult one = render_progressive(es, lights, ro, po);
  CHECK(one.passes == 1);
  CHECK(one.image.rgb == plain.image.rgb);
}

TEST_CASE("render: progressive photon mapping: more passes come closer to the path-traced reference") {
  // A coarse photon map (3000 photons, k = 32) blurs the Cornell Box's corners and edges: the
  // bias one render cannot lose. 12 passes shrink the disc to 0.64 r_1 and average 12 photon sets
  // and ray sets: the block error against the path tracer must fall, for kd-tree and block hashing.
  Scene scene = cornell_scene();
  PathTraceStats pst;
  const Image ref = path_traced(scene, 16, 1024, 2, pst);
  EmbreeScene es(scene, 2);
  LightSampler lights(scene);
  RenderOptions ro = small_options(16, 16, 32, 3, 2);
  std::vector<std::string> methods = {has_method("kdtree") ? "kdtree" : "bruteforce"};
  if (has_method("blockhash")) methods.push_back("blockhash");
  for (const std::string& m : methods) {
    ProgressiveOptions po;
    po.method = m;
    po.runtime = test::runtime();
    po.photons.photons = 3000;
    po.photons.seed = 3;
    po.photons.threads = 2;
    std::vector<double> errs;
    std::vector<int> reported;
    po.passes = 12;
    ProgressiveResult r = render_progressive(es, lights, ro, po, nullptr, [&](const PassReport& rep, const Image& img) {
      reported.push_back(rep.pass);
      errs.push_back(block_error(img, ref, 4).relative_rmse);
      if (m == "blockhash" && rep.pass > 1) CHECK(rep.rebuilt);  // the index rebuilt in place
    });
    REQUIRE(r.passes == 12);
    REQUIRE(reported.size() == 12);
    MESSAGE(m << ": 4x4-block relative RMSE vs path tracer: 1 pass " << errs[0] << ", 4 passes " << errs[3]
              << ", 12 passes " << errs[11]);
    CHECK(errs[11] < 0.8 * errs[0]);
    CHECK(errs[3] < errs[0]);
  }
}

TEST_CASE("render: bhcl render --passes: progress, periodic EXR, stats and argument errors") {
  std::string exr = test::tmp_path("cli_ppm.exr"), json = test::tmp_path("cli_ppm.json");
  std::string out = test::run_bhcl_ok("render --scene cornell --method bruteforce --photons 1500 --gather 2 --k 8 "
                          "--size 12x8 --passes 3 --exr-every 2 --quiet --out " + exr + " --stats " + json);
  CHECK(out.find("pass 2/3") != std::string::npos);
  CHECK(out.find("(mean of 2 passes)") != std::string::npos);
  CHECK(read_exr(exr).width == 12);
  std::ifstream s(json);
  const nlohmann::json j = nlohmann::json::parse(s);
  CHECK(j.at("passes") == 3);
  CHECK(j.at("exr_written") == 1);
  CHECK(j.at("pass_reports").size() == 3);
  CHECK(j.at("pass_reports")[2].at("radius_scale2").get<double>() < 1.0);
  // --time alone: at least one pass, as many as fit.
  CHECK(test::run_bhcl("render --method bruteforce --photons 1000 --gather 1 --k 4 --size 8x8 --time 0.01 --quiet "
                       "--out " + exr, &out) == 0);
  CHECK(out.find("pass 1") != std::string::npos);
  const std::string base = "render --method bruteforce --photons 1000 --size 8x8 --quiet --out " + exr;
  struct Bad {
    const char* args;
    const char* says;
  };
  for (const Bad& b : {Bad{" --passes 0", "--passes"}, Bad{" --passes 2 --alpha 1", "--alpha must be in (0, 1)"},
                       Bad{" --passes 2 --alpha 0", "--alpha must be in (0, 1)"},
                       Bad{" --alpha 0.5", "--alpha applies only to a progressive render"},
                       Bad{" --exr-every 2", "--exr-every applies only to a progressive render"},
                       Bad{" --passes 2 --exr-every 0", "--exr-every"},
                       Bad{" --time -1", "--time must be a positive number"},
                       Bad{" --time 0", "--time must be a positive number"}}) {
    INFO(b.args);
    CHECK(test::run_bhcl(base + b.args, &out) == 2);
    CHECK_MESSAGE(out.find(b.says) != std::string::npos, out);
  }
  CHECK(test::run_bhcl("render --compare --passes 2 --photons 1000 --size 8x8 --quiet --out " + exr, &out) == 2);
  CHECK(out.find("--passes does not apply with --compare") != std::string::npos);
}

TEST_CASE("render: the density estimate inside the query equals the host estimate from the lists, every method") {
  // Tolerance: relative 2e-5 of the estimate plus 1e-6 of the largest estimate (float: the
  // device sums in the same order as the host, the mean/var discs in float where the host uses
  // double; a photon exactly on the disc's rim may then fall the other way, worth at most a
  // filter weight of ~0 for cone/Epanechnikov, hence the absolute part).
  Scene scene = cornell_scene();
  EmbreeScene es(scene, 2);
  LightSampler lights(scene);
  PhotonMaps maps = trace_photons(es, lights, 6000, 5, 2);
  PhotonMap& map = *maps.global;
  // Queries: photon positions nudged (dense regions) and points spread over the box; normals
  // pointing every way, so that the facing test keeps some photons and drops others.
  std::vector<float> qs, ns;
  std::uint64_t st = 99;
  auto u = [&]() {
    st = st * 6364136223846793005ull + 1442695040888963407ull;
    return float(double(st >> 11) / double(1ull << 53));
  };
  for (std::size_t i = 0; i < 600; ++i) {
    const float* p = &map.positions()[3 * ((i * 9973) % map.size())];
    for (int c = 0; c < 3; ++c) qs.push_back(i % 3 == 0 ? u() * 550.0f : p[c] + (u() - 0.5f) * 5.0f);
    Vec3 n = normalize(Vec3{u() - 0.5f, u() - 0.5f, u() - 0.5f});
    if (i % 4 == 0) n = Vec3{0, 1, 0};  // the floor's normal: most photons face it
    ns.insert(ns.end(), {n.x, n.y, n.z});
  }
  const std::size_t n = qs.size() / 3;
  for (const std::string& m : method_names()) {
    map.build_index(m, test::runtime());
    for (float max_r : {INFINITY, 40.0f})
      for (float scale2 : {1.0f, 0.45f})
        for (RadiusEstimator re : {RadiusEstimator::Kth, RadiusEstimator::Mean, RadiusEstimator::Variance})
          for (DensityFilter f : {DensityFilter::Box, DensityFilter::Cone, DensityFilter::Epanechnikov}) {
            const DensityEstimator est{re, f};
            INFO(m << " " << estimator_name(est) << " max_radius " << max_r << " scale2 " << scale2);
            SearchParams sp = test::knn_params(24);
            sp.max_radius = max_r;
            KnnResult lists;
            map.query(qs.data(), n, sp, lists);
            DensityResult fused;
            map.estimate(qs.data(), ns.data(), n, sp, est, scale2, fused);
            REQUIRE(fused.n == n);
            CHECK(fused.bytes_read_back == 16 * n);
            std::vector<Vec3> host(n);
            double top = 0;
            for (std::size_t q = 0; q < n; ++q) {
              host[q] = map.radiance(lists, q, Vec3{ns[3 * q], ns[3 * q + 1], ns[3 * q + 2]}, Vec3{1, 1, 1}, max_r,
                                     est, scale2);
              top = std::max<double>(top, host[q].x);
            }
            REQUIRE(top > 0);
            std::size_t bad = 0;
            for (std::size_t q = 0; q < n; ++q) {
              const float s = map.power_scale() / kPi;
              const float got[3] = {fused.estimate[3 * q] * s, fused.estimate[3 * q + 1] * s, fused.estimate[3 * q + 2] * s};
              const float want[3] = {host[q].x, host[q].y, host[q].z};
              for (int c = 0; c < 3; ++c)
                if (std::fabs(got[c] - want[c]) > 2e-5 * std::fabs(want[c]) + 1e-6 * top) {
                  if (bad++ < 3) MESSAGE("query " << q << " channel " << c << ": fused " << got[c] << ", lists " << want[c]);
                }
            }
            CHECK(bad == 0);
          }
  }
  // Misuse: weights of another point set, a non-finite normal, a bad scale.
  map.build_index("bruteforce", test::runtime());
  std::vector<float> w(3 * 10, 1.0f);
  CHECK_THROWS_WITH_AS(DensityWeights(*map.index(), w.data(), w.data(), 10), doctest::Contains("10 points given"), Error);
  std::vector<float> bad_n = ns;
  bad_n[3 * 7 + 1] = NAN;
  DensityResult r;
  CHECK_THROWS_WITH_AS(map.estimate(qs.data(), bad_n.data(), n, {}, {}, 1.0f, r), doctest::Contains("query 7"), Error);
  CHECK_THROWS_WITH_AS(map.estimate(qs.data(), ns.data(), n, {}, {}, 1.5f, r), doctest::Contains("radius_scale2"), Error);
}

TEST_CASE("render: shading with the fused estimate matches shading from the lists") {
  // The same rays and photons: the image from the estimates inside the query and the one from
  // the lists differ by float rounding only (relative 1e-4 per pixel).
  Scene scene = cornell_scene();
  EmbreeScene es(scene, 2);
  LightSampler lights(scene);
  PhotonMaps maps = trace_photons(es, lights, 4000, 2, 2);
  maps.global->build_index(has_method("kdtree") ? "kdtree" : "bruteforce", test::runtime());
  RenderOptions ro;
  ro.width = ro.height = 16;
  ro.gather = 8;
  ro.search.k = 16;
  ro.threads = 2;
  ro.radius_scale2 = 0.7f;
  RenderStats s1, s2;
  const Image lists = FinalGatherRenderer(es, lights, *maps.global, nullptr, ro).render(s1);
  ro.fused_estimate = true;
  const Image fused = FinalGatherRenderer(es, lights, *maps.global, nullptr, ro).render(s2);
  CHECK(s2.result_bytes == 16 * s2.queries);
  CHECK(s1.result_bytes == s1.queries * (8 * 16 + 4));
  for (std::size_t i = 0; i < lists.rgb.size(); ++i)
    CHECK(fused.rgb[i] == doctest::Approx(lists.rgb[i]).epsilon(1e-4).scale(1e-3));
}


namespace {

// A 100 x 100 mm floor (y = 0, facing up), optionally a wall along its edge x = 0 (facing +x), and
// a light off to the side facing up (so that no point of the floor or wall gets direct light).
Scene boundary_scene(bool wall) {
  Scene s;
  s.name = wall ? "floor and wall" : "floor";
  Material white, light;
  white.name = "white";
  white.kd = {1, 1, 1};
  light.name = "light";
  light.kd = {0, 0, 0};
  light.emission = {1, 1, 1};
  const auto w = s.add_material(white), l = s.add_material(light);
  s.add_quad({0, 0, 0}, {0, 0, 100}, {100, 0, 100}, {100, 0, 0}, w);
  if (wall) s.add_quad({0, 0, 0}, {0, 100, 0}, {0, 100, 100}, {0, 0, 100}, w);
  s.add_quad({200, 300, 40}, {200, 300, 60}, {220, 300, 60}, {220, 300, 40}, l);
  return s;
}

// Photons of power 1 on a 100 x 100 square, one per 0.5 mm cell (jittered): at(u, v) maps the
// square to the surface; dir is where they came from; cls the surface's orientation class.
void add_surface_photons(std::vector<PhotonRecord>& recs, Rng& rng, Vec3 (*at)(float, float), Vec3 dir, int cls) {
  for (int j = 0; j < 200; ++j)
    for (int i = 0; i < 200; ++i) {
      const Vec3 x = at((i + rng.uniform()) * 0.5f, (j + rng.uniform()) * 0.5f);
      PhotonRecord r;
      r.position[0] = x.x;
      r.position[1] = x.y;
      r.position[2] = x.z;
      r.set_power({1, 1, 1});
      r.set_direction(normalize(dir));
      r.flags = 0;
      r.set_surface_class(cls);
      recs.push_back(r);
    }
}

// The caustic-map estimate (the only light these scenes give: no gather, no direct light) at floor
// points; lists or fused, with or without the boundary correction.
std::vector<double> floor_estimates(const EmbreeScene& es, const LightSampler& lights, const PhotonMap& map,
                                    const std::vector<Vec3>& xs, bool fused, bool boundary) {
  RenderOptions ro;
  ro.gather = 0;
  ro.shadow_rays = 1;
  ro.caustic_k = 64;
  ro.threads = 2;
  ro.fused_estimate = fused;
  ro.boundary_correction = boundary;
  const PhotonMap empty("global", {}, 1.0f);
  FinalGatherRenderer fg(es, lights, empty, &map, ro);
  std::vector<SurfacePoint> pts;
  for (const Vec3& x : xs) {
    SurfacePoint p;
    p.x = x;
    p.n = {0, 1, 0};
    p.kd = {1, 1, 1};
    p.prim = 0;  // the floor's first triangle (the plane raster covers both)
    pts.push_back(p);
  }
  RenderStats st;
  std::vector<double> out;
  for (const Vec3& l : fg.shade(pts, st)) out.push_back(l.x);
  return out;
}

double mean_of(const std::vector<double>& v, std::size_t b, std::size_t e) {
  double s = 0;
  for (std::size_t i = b; i < e; ++i) s += v[i];
  return s / static_cast<double>(e - b);
}

// Interior points (x, z in [30, 70]), then points on the edge x = 0 (z in [20, 80]), then the
// four corners: counts 40, 60, 4.
std::vector<Vec3> interior_edge_corner_points() {
  std::vector<Vec3> xs;
  for (int i = 0; i < 40; ++i) xs.push_back({30 + (i % 8) * 5.0f, 0, 30 + (i / 8) * 10.0f});
  for (int i = 0; i < 60; ++i) xs.push_back({0, 0, 20 + i * 1.0f});
  for (Vec3 c : {Vec3{0, 0, 0}, Vec3{100, 0, 0}, Vec3{0, 0, 100}, Vec3{100, 0, 100}}) xs.push_back(c);
  return xs;
}

}  // namespace

TEST_CASE("render: the boundary-corrected estimate at a lit quad's edge and corner equals its interior's") {
  // Uniform irradiance on a lone quad: a disc at the edge has half its area on the quad, at a
  // corner a quarter, so the plain estimate reads 1/2 and 1/4 of the interior's there; divided by
  // the disc's area on the quad it reads the interior's.
  Scene scene = boundary_scene(false);
  EmbreeScene es(scene, 2);
  LightSampler lights(scene);
  Rng rng(41, 41, 41);
  std::vector<PhotonRecord> recs;
  add_surface_photons(recs, rng, [](float u, float v) { return Vec3{u, 0, v}; }, {0.3f, 1, 0.2f}, 2);
  PhotonMap map("floor", recs, 1.0f);
  map.build_index(has_method("kdtree") ? "kdtree" : "bruteforce", test::runtime());
  const std::vector<Vec3> xs = interior_edge_corner_points();
  for (bool fused : {false, true}) {
    CAPTURE(fused);
    const std::vector<double> plain = floor_estimates(es, lights, map, xs, fused, false);
    const std::vector<double> fixed = floor_estimates(es, lights, map, xs, fused, true);
    const double in_plain = mean_of(plain, 0, 40), in_fixed = mean_of(fixed, 0, 40);
    // In the interior the correction changes nothing (every disc wholly on the quad).
    CHECK(in_fixed == doctest::Approx(in_plain).epsilon(1e-6));
    const double edge_plain = mean_of(plain, 40, 100) / in_plain, corner_plain = mean_of(plain, 100, 104) / in_plain;
    const double edge_fixed = mean_of(fixed, 40, 100) / in_fixed, corner_fixed = mean_of(fixed, 100, 104) / in_fixed;
    MESSAGE("edge / interior: plain " << edge_plain << ", corrected " << edge_fixed << "; corner / interior: plain "
                                      << corner_plain << ", corrected " << corner_fixed);
    CHECK(edge_plain == doctest::Approx(0.5).epsilon(0.06));
    CHECK(corner_plain == doctest::Approx(0.25).epsilon(0.12));
    CHECK(edge_fixed == doctest::Approx(1.0).epsilon(0.02));
    CHECK(corner_fixed == doctest::Approx(1.0).epsilon(0.03));
  }
}

TEST_CASE("render: the boundary-corrected estimate leaves out the photons of an adjoining wall") {
  // A wall stands on the floor's edge x = 0; its photons arrive from above it, so they pass the
  // floor's facing test: without the correction the floor's edge reads its own half disc plus the
  // wall's photons in the sphere; with it, the floor's photons over the floor's half disc only.
  Scene scene = boundary_scene(true);
  EmbreeScene es(scene, 2);
  LightSampler lights(scene);
  Rng rng(42, 42, 42);
  std::vector<PhotonRecord> recs;
  add_surface_photons(recs, rng, [](float u, float v) { return Vec3{u, 0, v}; }, {0.3f, 1, 0.2f}, 2);
  add_surface_photons(recs, rng, [](float u, float v) { return Vec3{0, u, v}; }, {0.6f, 0.8f, 0}, 0);
  PhotonMap map("floor and wall", recs, 1.0f);
  map.build_index(has_method("kdtree") ? "kdtree" : "bruteforce", test::runtime());
  const std::vector<Vec3> xs = interior_edge_corner_points();
  for (bool fused : {false, true}) {
    CAPTURE(fused);
    const std::vector<double> plain = floor_estimates(es, lights, map, xs, fused, false);
    const std::vector<double> fixed = floor_estimates(es, lights, map, xs, fused, true);
    const double edge_plain = mean_of(plain, 40, 100) / mean_of(plain, 0, 40);
    const double edge_fixed = mean_of(fixed, 40, 100) / mean_of(fixed, 0, 40);
    MESSAGE("floor edge by the wall / interior: plain " << edge_plain << ", corrected " << edge_fixed);
    CHECK(edge_plain > 0.6);  // the wall's photons counted
    CHECK(edge_fixed == doctest::Approx(1.0).epsilon(0.02));
  }
}

TEST_CASE("render: the boundary correction's rasters: the floor under an open-bottomed block is closed, under glass is glass") {
  // The specular Cornell box: its mirror block stands on the floor with no bottom face, the glass
  // block likewise. A disc on the floor just outside the mirror block's foot has part of its area
  // under the block (no photon lands there); a disc just inside the glass block's foot has part
  // outside the glass (its photons are keyed apart); a disc at a wall's foot half. All get a factor
  // above 1 (the cone filter's integral over the whole disc over that over its part on the
  // surface); a disc in the open floor none.
  Scene scene = load_scene("cornell-specular");
  EmbreeScene es(scene, 2);
  const SurfaceAreaMap areas(es, 2);
  std::uint32_t floor = 0;
  for (std::uint32_t t = 0; t < scene.triangles.size(); ++t)
    if (scene.material_of(t).is_diffuse() && scene.geometric_normal(t).y > 0.99f &&
        scene.vertices[scene.triangles[t][0]].y < 1) floor = t;
  const float r2 = 10.0f * 10.0f;
  auto f = [&](Vec3 x, bool in_glass) { return areas.factor(floor, false, x, in_glass, r2, DensityFilter::Cone); };
  CHECK(f({400, 0, 100}, false) == 1.0f);  // the open floor
  CHECK(f({185, 0, 169}, true) == 1.0f);   // the middle of the glass block's footprint
  CHECK(f({0, 0, 300}, false) == doctest::Approx(2.0).epsilon(0.03));  // the right wall's foot: half a disc
  CHECK(f({0, 0, 559.2f}, false) == doctest::Approx(4.0).epsilon(0.05));  // the back corner: a quarter
  // 2 mm outside the mirror block's face (423, 247) - (472, 406): part of the disc is under it.
  const float fm = f({449.4f, 0, 325.9f}, false);
  CHECK(fm > 1.3f);
  CHECK(fm < 1.8f);
  // 2 mm inside the glass block's face (130, 65) - (290, 114): part of the disc is outside the glass.
  const float fg = f({209.4f, 0, 91.4f}, true);
  CHECK(fg > 1.3f);
  CHECK(fg < 1.8f);
  // The ceiling above the light (closed by the light's back) against the open ceiling beside it.
  std::uint32_t ceiling = 0;
  for (std::uint32_t t = 0; t < scene.triangles.size(); ++t)
    if (scene.material_of(t).is_diffuse() && scene.geometric_normal(t).y < -0.99f) ceiling = t;
  CHECK(areas.factor(ceiling, false, {213 - 2.0f, 548.8f, 280}, false, r2, DensityFilter::Cone) > 1.3f);
  CHECK(areas.factor(ceiling, false, {100, 548.8f, 280}, false, r2, DensityFilter::Cone) == 1.0f);
  // Back sides, unknown triangles and no disc: no correction.
  CHECK(areas.factor(floor, true, {0, 0, 300}, false, r2, DensityFilter::Cone) == 1.0f);
  CHECK(areas.factor(static_cast<std::uint32_t>(scene.triangles.size()), false, {0, 0, 300}, false, r2,
                     DensityFilter::Cone) == 1.0f);
  CHECK(areas.factor(floor, false, {0.0f, 0, 300}, false, 0.0f, DensityFilter::Cone) == 1.0f);
}

#endif  // BHCL_HAVE_RENDER
