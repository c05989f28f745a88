// Meshes: the hierarchy finds exactly what testing every triangle finds; OBJ files load (and bad ones are refused by
// line); the head has its parts where a head has them, its expressions move the right regions, a blink covers the
// eye, performances ease between keys, and its skin has pores of the stated size.
#include "stage/sim/mesh.h"

#include <Eigen/Geometry>
#include <cmath>
#include <fstream>
#include <iterator>
#include <map>
#include <random>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/sim/head.h"
#include "stage/sim/performance_yaml.h"

namespace stage::sim {
namespace {

using ::testing::HasSubstr;

// Brute force: every triangle, Moeller-Trumbore in double precision.
double BruteForceT(const TriangleMesh& m, const Eigen::Vector3f& o, const Eigen::Vector3f& d) {
  double best = INFINITY;
  const Eigen::Vector3d od = o.cast<double>(), dd = d.cast<double>();
  for (const auto& t : m.triangles) {
    const Eigen::Vector3d a = m.positions[t[0]].cast<double>();
    const Eigen::Vector3d e1 = m.positions[t[1]].cast<double>() - a, e2 = m.positions[t[2]].cast<double>() - a;
    const Eigen::Vector3d p = dd.cross(e2);
    const double det = e1.dot(p);
    if (std::abs(det) < 1e-15) continue;
    const Eigen::Vector3d s = od - a;
    const double u = s.dot(p) / det;
    const Eigen::Vector3d q = s.cross(e1);
    const double v = dd.dot(q) / det;
    const double t_hit = e2.dot(q) / det;
    if (u >= 0 && v >= 0 && u + v <= 1 && t_hit > 1e-4) best = std::min(best, t_hit);
  }
  return best;
}

TEST(MeshTest, TheHierarchyFindsWhatEveryTriangleFinds) {
  auto head = HeadModel::Procedural(7, 64);
  MeshSubject subject(head->neutral(), nullptr);
  std::mt19937 rng(3);
  std::uniform_real_distribution<float> u(-1, 1);
  int hits = 0;
  for (int i = 0; i < 400; ++i) {
    const Eigen::Vector3f origin = Eigen::Vector3f(u(rng), u(rng), u(rng)).normalized() * 600;
    const Eigen::Vector3f target(60 * u(rng), 90 * u(rng), 60 * u(rng));
    const Eigen::Vector3f d = (target - origin).normalized();
    const Hit h = subject.Intersect(origin, d);
    const double expected = BruteForceT(head->neutral(), origin, d);
    ASSERT_EQ(h.hit, std::isfinite(expected)) << i;
    if (h.hit) {
      ++hits;
      EXPECT_NEAR(h.t, expected, 1e-3) << i;
      // Shadow ray: blocked exactly when something lies between.
      EXPECT_TRUE(subject.Occluded(origin, origin + d * (h.t + 1)));
      EXPECT_FALSE(subject.Occluded(origin, origin + d * (h.t - 1)));
    }
  }
  EXPECT_GT(hits, 300);
}

TEST(MeshTest, ReadsObjFilesAndNamesTheLineOfAnError) {
  const std::string path = ::testing::TempDir() + "/quad.obj";
  {
    std::ofstream f(path);
    f << "# a unit quad\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1 2/2 3/3 4/4\n";
  }
  auto mesh = ReadObj(path);
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  EXPECT_EQ(mesh->triangles.size(), 2u);
  EXPECT_EQ(mesh->positions.size(), 4u);
  MeshSubject quad(*mesh, nullptr);
  const Hit h = quad.Intersect({0.25f, 0.75f, 5}, {0, 0, -1});
  ASSERT_TRUE(h.hit);
  EXPECT_NEAR(h.uv.x(), 0.25f, 1e-5);
  EXPECT_NEAR(h.uv.y(), 0.75f, 1e-5);

  {
    std::ofstream f(path);
    f << "v 0 0 0\nv 1 0 0\nf 1 2 7\n";
  }
  auto bad = ReadObj(path);
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(bad.status().message(), HasSubstr("quad.obj:3"));
  EXPECT_THAT(ReadObj(::testing::TempDir() + "/missing.obj").status().message(), HasSubstr("missing.obj"));
}

TEST(MeshTest, WrittenObjFilesKeepPartsAndMayHaveNoTextureCoordinates) {
  const std::string path = ::testing::TempDir() + "/parts.obj";
  TriangleMesh m;
  m.positions = {{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0}};
  m.triangles = {{0, 1, 2}, {0, 2, 3}};
  m.parts = {0, 1};
  ASSERT_TRUE(WriteObj(path, m, "two parts").ok());
  auto back = ReadObj(path);
  ASSERT_TRUE(back.ok()) << back.status();
  std::ifstream text(path);
  const std::string bytes((std::istreambuf_iterator<char>(text)), std::istreambuf_iterator<char>());
  EXPECT_EQ(bytes.find("vt "), std::string::npos) << "texture coordinates written for a mesh without them";
  EXPECT_NE(bytes.find("f 1 2 3"), std::string::npos) << bytes;
  EXPECT_EQ(back->parts, m.parts);
  EXPECT_FALSE(std::ifstream(path + ".partial").good()) << "the temporary file was left behind";
  // A mesh of one part is written without materials.
  m.parts = {0, 0};
  ASSERT_TRUE(WriteObj(path, m).ok());
  back = ReadObj(path);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_TRUE(back->parts.empty());
  EXPECT_TRUE(back->material_names.empty());
}

// Where the ray from far in front along -z first meets the head, at height y and lateral offset x.
Hit FromFront(const Subject& s, float x, float y) { return s.Intersect({x, y, 1000}, {0, 0, -1}); }

TEST(HeadTest, HasAHeadsProportionsAndParts) {
  auto head = HeadModel::Procedural(1);
  auto neutral = head->Posed({});
  // Nose: the front-most skin, well ahead of the cheeks.
  const float nose = FromFront(*neutral, 0, -10).point.z();
  const float cheek = FromFront(*neutral, 45, -10).point.z();
  EXPECT_GT(nose - cheek, 25) << "nose " << nose << " cheek " << cheek;
  // Width between the ears 140..180 mm; height of the face region (the ray from above) plausible.
  const Hit left = neutral->Intersect({1000, 0, 0}, {-1, 0, 0}), right = neutral->Intersect({-1000, 0, 0}, {1, 0, 0});
  const float width = left.point.x() - right.point.x();
  EXPECT_GT(width, 140);
  EXPECT_LT(width, 200);
  const Hit top = neutral->Intersect({0, 1000, 0}, {0, -1, 0});
  EXPECT_GT(top.point.y(), 100);
  EXPECT_LT(top.point.y(), 130);
  // The eyes are seen from the front (part 1, glossy) at their sockets.
  const float eye_x = std::sin(0.36f) * 90, eye_y = std::sin(0.10f) * 90;
  const Hit eye = FromFront(*neutral, eye_x, eye_y);
  ASSERT_TRUE(eye.hit);
  EXPECT_EQ(eye.part, 1);
  EXPECT_LT(eye.material.roughness, 0.1f);
}

TEST(HeadTest, AnIdentityDrawsAnotherPerformerWithTheSameLayout) {
  const HeadShape shipped = HeadShape::Drawn(0), other = HeadShape::Drawn(5);
  EXPECT_EQ(shipped.nose_mm, HeadShape{}.nose_mm);
  EXPECT_EQ(shipped.width_mm, HeadShape{}.width_mm);
  EXPECT_EQ(HeadShape::Drawn(5).nose_mm, other.nose_mm);  // the same identity, the same performer
  auto a = HeadModel::Procedural(1, 64), b = HeadModel::Procedural(1, 64, other);
  ASSERT_EQ(a->neutral().positions.size(), b->neutral().positions.size());
  EXPECT_EQ(a->neutral().uvs, b->neutral().uvs);
  EXPECT_EQ(a->neutral().triangles, b->neutral().triangles);
  double sum = 0, worst = 0;
  for (size_t v = 0; v < a->neutral().positions.size(); ++v) {
    const double d = (a->neutral().positions[v] - b->neutral().positions[v]).norm();
    sum += d;
    worst = std::max(worst, d);
  }
  const double mean = sum / static_cast<double>(a->neutral().positions.size());
  // Another face, not another species: millimetres apart on average, never more than a few centimetres.
  EXPECT_GT(mean, 1.0);
  EXPECT_LT(worst, 30.0);
  // Every proportion is within 2.5 standard deviations of the shipped head's.
  for (int identity = 1; identity < 50; ++identity) {
    const HeadShape s = HeadShape::Drawn(static_cast<uint64_t>(identity));
    EXPECT_NEAR(s.width_mm, shipped.width_mm, shipped.width_mm * 0.1 + 1e-3) << identity;
    EXPECT_NEAR(s.nose_mm, shipped.nose_mm, shipped.nose_mm * 0.5 + 1e-3) << identity;
    EXPECT_GT(s.jaw, 0) << identity;
  }
}

TEST(HeadTest, ExpressionsMoveTheirRegionsAndABlinkCoversTheEye) {
  auto head = HeadModel::Procedural(1);
  auto neutral = head->Posed({});
  const float eye_x = std::sin(0.36f) * 90, eye_y = std::sin(0.10f) * 90;
  HeadPose blink;
  blink.expression[ExpressionIndex("blink_left")] = 1;
  auto blinking = head->Posed(blink);
  EXPECT_EQ(FromFront(*blinking, eye_x, eye_y).part, 0) << "the left eyelid covers the left eye";
  EXPECT_EQ(FromFront(*blinking, -eye_x, eye_y).part, 1) << "the right eye stays open";

  HeadPose jaw;
  jaw.expression[ExpressionIndex("jaw_open")] = 1;
  auto open = head->Posed(jaw);
  // The chin drops: the lowest point of the face moves down by several mm.
  auto lowest = [](const MeshSubject& s) {
    float low = 0;
    for (const auto& p : s.mesh().positions) {
      if (p.z() > 40) low = std::min(low, p.y());
    }
    return low;
  };
  EXPECT_LT(lowest(*open), lowest(*neutral) - 8);
  // ... and the forehead does not move.
  EXPECT_NEAR(FromFront(*open, 0, 70).point.z(), FromFront(*neutral, 0, 70).point.z(), 1e-3);

  HeadPose brow;
  brow.expression[ExpressionIndex("brow_raise")] = 1;
  // Forehead wrinkles appear only with the expression: the detail normal varies more across the forehead.
  auto variation = [&](const HeadPose& pose) {
    auto s = head->Posed(pose);
    double sum = 0;
    for (int k = 0; k < 200; ++k) {
      const Hit h = FromFront(*s, 0.05f * k - 5, 35 + 0.125f * k);  // up the forehead
      sum += 1 - h.normal.dot(h.geometric_normal);                  // how far the detail tilts the normal
    }
    return sum;
  };
  EXPECT_GT(variation(brow), 1.5 * variation({}));
}

// With blood flow the cheeks flush with a smile (green and blue fall, where the smile works the face), and only then;
// without it the smile leaves the albedo alone.
TEST(HeadTest, BloodFlowFlushesTheCheeksOfASmile) {
  auto still = HeadModel::Procedural(1, 64), flushing = HeadModel::Procedural(1, 64, HeadShape(), 1.0f);
  std::array<float, kExpressionCount> smile{};
  smile[ExpressionIndex("smile_left")] = 1;
  // The left cheek (azimuth +0.5 rad, elevation -0.15 rad) and the right one, in the skin's layout.
  const Eigen::Vector2f left(0.5f / (2 * 3.14159265f) + 0.5f, -0.15f / 3.14159265f + 0.5f);
  const Eigen::Vector2f right(-0.5f / (2 * 3.14159265f) + 0.5f, left.y());
  const Eigen::Vector3f rest = flushing->Surface(left, 0, {}).material.albedo;
  const Eigen::Vector3f flushed = flushing->Surface(left, 0, smile).material.albedo;
  EXPECT_EQ(rest, still->Surface(left, 0, {}).material.albedo) << "no expression, no flush";
  EXPECT_NEAR(flushed.y() / rest.y(), 0.65, 0.01);
  EXPECT_NEAR(flushed.z() / rest.z(), 0.75, 0.01);
  EXPECT_GT(flushed.x(), rest.x());
  EXPECT_NEAR(
      flushing->Surface(right, 0, smile).material.albedo.y() / flushing->Surface(right, 0, {}).material.albedo.y(), 1,
      0.01)
      << "the other cheek stays";
  EXPECT_EQ(still->Surface(left, 0, smile).material.albedo, still->Surface(left, 0, {}).material.albedo);
}

TEST(HeadTest, PerformancesEaseBetweenKeysAndLoadFromYaml) {
  Performance p = Performance::Default();
  ASSERT_GE(p.keys.size(), 8u);
  // Every expression is used somewhere in the shipped script, and the head turns both ways.
  for (int e = 0; e < kExpressionCount; ++e) {
    float peak = 0;
    for (const auto& [t, pose] : p.keys) peak = std::max(peak, pose.expression[e]);
    EXPECT_EQ(peak, 1.0f) << ExpressionName(e);
  }
  const HeadPose mid = p.At(0.2);  // halfway from neutral to a brow raise
  EXPECT_NEAR(mid.expression[ExpressionIndex("brow_raise")], 0.5f, 1e-5);

  const std::string path = ::testing::TempDir() + "/perf.yaml";
  {
    std::ofstream f(path);
    f << "keys:\n  - {t: 0}\n  - {t: 1, jaw_open: 1, yaw: 10}\n";
  }
  auto loaded = Performance::FromYaml(path);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_NEAR(loaded->At(1).rotation_deg.x(), 10, 1e-6);
  {
    std::ofstream f(path);
    f << "keys:\n  - {t: 0}\n  - {t: 1, grin: 1}\n";
  }
  auto bad = Performance::FromYaml(path);
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(bad.status().message(), HasSubstr("keys[1]: unknown field \"grin\""));
  {
    std::ofstream f(path);
    f << "keys:\n  - {t: 0, sequence: warmup}\n  - {t: 1, jaw_open: 1}\n  - {t: 2, sequence: talk-1}\n";
  }
  auto named = Performance::FromYaml(path);
  ASSERT_TRUE(named.ok()) << named.status();
  EXPECT_EQ(named->SequenceAt(0.5), "warmup");
  EXPECT_EQ(named->SequenceAt(2.5), "talk-1");
  EXPECT_EQ(Performance::Default().SequenceAt(1), "");
}

TEST(HeadTest, RangeOfMotionWorksEveryExpressionInNamedSequencesUnderHeadMotion) {
  const Performance p = Performance::RangeOfMotion(7, 180);
  // 6 s sequences: 30, every group of 8 at least three times, named by group and round.
  ASSERT_EQ(p.sequences.size(), 30u);
  EXPECT_EQ(p.SequenceAt(-1), "");
  std::map<std::string, int> rounds;
  for (const auto& [start, name] : p.sequences) {
    const std::string group = name.substr(0, name.rfind('-'));
    ++rounds[group];
    EXPECT_EQ(p.SequenceAt(start + 3), name);
    // Each sequence starts at rest.
    for (float w : p.At(start).expression) EXPECT_EQ(w, 0.f) << name;
  }
  EXPECT_EQ(rounds.size(), 8u);
  for (const auto& [group, n] : rounds) EXPECT_GE(n, 3) << group;
  // Every expression reaches a strong weight somewhere, and the head turns and moves well within its range.
  std::array<float, kExpressionCount> peak{};
  Eigen::Vector3f max_turn = Eigen::Vector3f::Zero(), max_move = Eigen::Vector3f::Zero();
  for (double t = 0; t < 180; t += 0.1) {
    const HeadPose pose = p.At(t);
    for (int e = 0; e < kExpressionCount; ++e) peak[e] = std::max(peak[e], pose.expression[e]);
    max_turn = max_turn.cwiseMax(pose.rotation_deg.cwiseAbs());
    max_move = max_move.cwiseMax(pose.translation_mm.cwiseAbs());
  }
  for (int e = 0; e < kExpressionCount; ++e) EXPECT_GT(peak[e], 0.8f) << ExpressionName(e);
  EXPECT_GT(max_turn.x(), 20);
  EXPECT_LE(max_turn.x(), 30);
  EXPECT_GT(max_move.norm(), 8);
  // The same seed draws the same performance; another draws another.
  EXPECT_EQ(Performance::RangeOfMotion(7, 180).At(42.3).rotation_deg, p.At(42.3).rotation_deg);
  EXPECT_NE(Performance::RangeOfMotion(8, 180).At(42.3).rotation_deg, p.At(42.3).rotation_deg);
}

TEST(HeadTest, APerformanceWrittenAsYamlReadsBackToTheBit) {
  // A range of motion longer than the rig's 180 s (more rounds of every group), written and read back.
  const Performance p = Performance::RangeOfMotion(7, 600);
  ASSERT_EQ(p.sequences.size(), 100u);
  const std::string path = ::testing::TempDir() + "/range-of-motion.yaml";
  ASSERT_TRUE(WritePerformanceYaml(p, path).ok());
  auto read = Performance::FromYaml(path);
  ASSERT_TRUE(read.ok()) << read.status();
  ASSERT_EQ(read->keys.size(), p.keys.size());
  for (size_t k = 0; k < p.keys.size(); ++k) {
    EXPECT_EQ(read->keys[k].first, p.keys[k].first) << k;
    EXPECT_EQ(read->keys[k].second.expression, p.keys[k].second.expression) << k;
    EXPECT_EQ(read->keys[k].second.rotation_deg, p.keys[k].second.rotation_deg) << k;
    EXPECT_EQ(read->keys[k].second.translation_mm, p.keys[k].second.translation_mm) << k;
  }
  EXPECT_EQ(read->sequences, p.sequences);
  EXPECT_EQ(read->At(421.37).expression, p.At(421.37).expression);
  EXPECT_EQ(read->SequenceAt(421.37), p.SequenceAt(421.37));

  // A sequence that starts between keys cannot be said in the file's terms; an unwritable path is named.
  Performance between = p;
  between.sequences.emplace_back(0.25, "odd-1");
  EXPECT_THAT(WritePerformanceYaml(between, path).message(), HasSubstr("\"odd-1\" starts at 0.25 s, between keys"));
  EXPECT_THAT(WritePerformanceYaml(p, ::testing::TempDir() + "/no-such-dir/p.yaml").message(),
              HasSubstr("no-such-dir/p.yaml: cannot write"));
}

TEST(HeadTest, PoresAreTwoToTenTexelsAcrossAt4K) {
  auto head = HeadModel::Procedural(1);
  // Scan a row of the skin map at 4096 texels and measure each pore's width (where the height dips).
  std::vector<int> widths;
  int run = 0;
  for (int x = 0; x < 4096; ++x) {
    const float h = head->Surface(Eigen::Vector2f((x + 0.5f) / 4096, 0.62f), 0, {}).height;
    if (h < -1e-4f) {
      ++run;
    } else if (run > 0) {
      widths.push_back(run);
      run = 0;
    }
  }
  ASSERT_GT(widths.size(), 50u);
  // A chord near a pore's rim is shorter than its diameter; two pores that touch make one longer run.
  int within = 0, longer = 0;
  for (int w : widths) {
    within += w >= 2 && w <= 10;
    longer += w > 10;
  }
  EXPECT_GT(within, static_cast<int>(widths.size()) * 3 / 4);
  EXPECT_LT(longer, static_cast<int>(widths.size()) / 20);
}

}  // namespace
}  // namespace stage::sim
