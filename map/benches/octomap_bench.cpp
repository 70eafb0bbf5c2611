// The project's anchor benchmark for OctoMap, kept here so the server benches (benches/common)
// can build it from a clean clone; the numbers in research/octomap.md §8 were made with it.
//
// Build: g++ -O2 -DNDEBUG -std=c++17 -o /tmp/octomap_bench octomap_bench.cpp -loctomap -loctomath
//   (Debian bookworm: apt-get install liboctomap-dev -> liboctomap 1.9.7, single-threaded, no OpenMP.
//    OctoMap's insertion code is header templates, so these compile flags decide its speed:
//    upstream's Release flags are "-O3 -funroll-loops -DNDEBUG"; Debian's .so is built -O2 without NDEBUG.)
//
// Anchor benchmark for OctoMap (the reference our Rust octomap must match and beat).
//
//   octomap_bench insert <in.graph|in.scans> [-res R=0.1] [-m maxrange=-1] [-discretize] [-rays]
//                        [-lazy] [-n maxscans] [-o outprefix] [-export-scans out.scans]
//       Reads scans, inserts each with OcTree::insertPointCloud (or insertPointCloudRays with -rays),
//       times only the insertion loop, prints stats, writes <outprefix>.ot (full log-odds, pruned,
//       before max-likelihood) and then <outprefix>.bt (writeBinary: toMaxLikelihood+prune+write).
//       .graph scans are pre-transformed exactly as graph2tree does (not timed), so the tree equals
//       graph2tree's for the same -res/-m.
//   octomap_bench read <map.bt|map.ot> [-repeat N=5]
//       Times reading the file and iterating all leaves (count, occupied/free, volume, key hash).
//   octomap_bench cmp <a.bt|a.ot> <b.bt|b.ot>
//       Exact voxel-volume confusion matrix {occupied,free,unknown}^2 between two maps of equal
//       resolution, by simultaneous descent of both trees (a pruned leaf acts as 8 equal children).
//
// ".scans" format (ours, documented in research/octomap.md): little-endian records until EOF:
//   u32 n; f64 origin_x, origin_y, origin_z; n x (f32 x, f32 y, f32 z)   -- points in world frame.
// OctoMap works in f32: the origin is cast to float before insertion.
#include <octomap/octomap.h>
#include <octomap/OcTree.h>
#include <algorithm>
#include <chrono>
#include <cinttypes>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <fstream>
#include <string>
#include <vector>

using namespace octomap;
using Clock = std::chrono::steady_clock;
static double secs(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double>(b - a).count();
}
// process CPU time: less sensitive than wall time to other processes competing for the cores
static double cpu_now() {
  timespec ts;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

struct Scan {
  point3d origin;
  Pointcloud points;
};

static bool ends_with(const std::string& s, const std::string& suf) {
  return s.size() >= suf.size() && s.compare(s.size() - suf.size(), suf.size(), suf) == 0;
}

static bool load_graph(const std::string& fn, std::vector<Scan>& scans, int maxscans) {
  ScanGraph graph;
  if (!graph.readBinary(fn)) return false;
  for (ScanGraph::iterator it = graph.begin(); it != graph.end(); ++it) {
    if (maxscans > 0 && (int)scans.size() >= maxscans) break;
    // identical to graph2tree.cpp (OctoMap 1.9.7/1.10.0):
    pose6d frame_origin = (*it)->pose;
    point3d sensor_origin = frame_origin.inv().transform((*it)->pose.trans());
    Scan s;
    s.points = *((*it)->scan);
    s.points.transform(frame_origin);
    s.origin = frame_origin.transform(sensor_origin);
    scans.push_back(std::move(s));
  }
  return true;
}

static bool load_scans(const std::string& fn, std::vector<Scan>& scans, int maxscans) {
  FILE* f = fopen(fn.c_str(), "rb");
  if (!f) return false;
  for (;;) {
    if (maxscans > 0 && (int)scans.size() >= maxscans) break;
    uint32_t n;
    if (fread(&n, 4, 1, f) != 1) break;
    double o[3];
    if (fread(o, 8, 3, f) != 3) { fclose(f); return false; }
    std::vector<float> buf(3 * (size_t)n);
    if (n && fread(buf.data(), 4, buf.size(), f) != buf.size()) { fclose(f); return false; }
    Scan s;
    s.origin = point3d((float)o[0], (float)o[1], (float)o[2]);
    s.points.reserve(n);
    for (uint32_t i = 0; i < n; ++i) s.points.push_back(buf[3 * i], buf[3 * i + 1], buf[3 * i + 2]);
    scans.push_back(std::move(s));
  }
  fclose(f);
  return true;
}

static bool write_scans(const std::string& fn, const std::vector<Scan>& scans) {
  FILE* f = fopen(fn.c_str(), "wb");
  if (!f) return false;
  for (const Scan& s : scans) {
    uint32_t n = (uint32_t)s.points.size();
    double o[3] = {s.origin.x(), s.origin.y(), s.origin.z()};
    fwrite(&n, 4, 1, f);
    fwrite(o, 8, 3, f);
    for (size_t i = 0; i < s.points.size(); ++i) {
      float p[3] = {s.points[i].x(), s.points[i].y(), s.points[i].z()};
      fwrite(p, 4, 3, f);
    }
  }
  fclose(f);
  return true;
}

struct LeafStats {
  size_t leaves = 0, occ = 0, fr = 0, full_depth = 0;
  double vol_occ = 0, vol_free = 0;
  uint64_t hash = 1469598103934665603ULL;  // FNV-1a over (key, depth, occupied) in iteration order
};

static LeafStats leaf_stats(const OcTree& t) {
  LeafStats st;
  for (OcTree::leaf_iterator it = t.begin_leafs(), end = t.end_leafs(); it != end; ++it) {
    ++st.leaves;
    double s = it.getSize();
    bool occ = t.isNodeOccupied(*it);
    if (occ) { ++st.occ; st.vol_occ += s * s * s; } else { ++st.fr; st.vol_free += s * s * s; }
    if (it.getDepth() == t.getTreeDepth()) ++st.full_depth;
    const OcTreeKey& k = it.getKey();
    uint64_t v[5] = {k[0], k[1], k[2], it.getDepth(), (uint64_t)occ};
    for (uint64_t x : v) { st.hash ^= x; st.hash *= 1099511628211ULL; }
  }
  return st;
}

static void print_stats(const char* label, const OcTree& t) {
  LeafStats st = leaf_stats(t);
  printf("%s: nodes %zu leaves %zu (occupied %zu, free %zu, at depth 16: %zu) vol_occ %.4f m3 vol_free %.4f m3 memoryUsage %zu B leafhash %016" PRIx64 "\n",
         label, t.size(), st.leaves, st.occ, st.fr, st.full_depth, st.vol_occ, st.vol_free, t.memoryUsage(), st.hash);
}

static OcTree* read_tree(const std::string& fn) {
  if (ends_with(fn, ".bt")) {
    OcTree* t = new OcTree(0.1);
    if (!t->readBinary(fn)) { delete t; return nullptr; }
    return t;
  }
  AbstractOcTree* a = AbstractOcTree::read(fn);
  OcTree* t = dynamic_cast<OcTree*>(a);
  if (!t) delete a;
  return t;
}

static int cmd_insert(int argc, char** argv) {
  std::string in = argv[2], outprefix, export_fn;
  double res = 0.1, maxrange = -1.0;
  bool discretize = false, rays = false, lazy = false;
  int maxscans = -1;
  for (int i = 3; i < argc; ++i) {
    std::string a = argv[i];
    if (a == "-res") res = atof(argv[++i]);
    else if (a == "-m") maxrange = atof(argv[++i]);
    else if (a == "-discretize") discretize = true;
    else if (a == "-rays") rays = true;
    else if (a == "-lazy") lazy = true;
    else if (a == "-n") maxscans = atoi(argv[++i]);
    else if (a == "-o") outprefix = argv[++i];
    else if (a == "-export-scans") export_fn = argv[++i];
    else { fprintf(stderr, "unknown option %s\n", a.c_str()); return 2; }
  }
  std::vector<Scan> scans;
  auto t0 = Clock::now();
  bool ok = ends_with(in, ".graph") ? load_graph(in, scans, maxscans) : load_scans(in, scans, maxscans);
  auto t1 = Clock::now();
  if (!ok) { fprintf(stderr, "cannot read %s\n", in.c_str()); return 1; }
  size_t npts = 0;
  for (const Scan& s : scans) npts += s.points.size();
  printf("input %s: scans %zu points %zu (load+transform %.3f s)\n", in.c_str(), scans.size(), npts, secs(t0, t1));
  if (!export_fn.empty()) {
    write_scans(export_fn, scans);
    printf("exported %s\n", export_fn.c_str());
  }

  OcTree tree(res);
  double c2 = cpu_now();
  auto t2 = Clock::now();
  for (const Scan& s : scans) {
    if (rays) tree.insertPointCloudRays(s.points, s.origin, maxrange, lazy);
    else tree.insertPointCloud(s.points, s.origin, maxrange, lazy, discretize);
  }
  if (lazy) tree.updateInnerOccupancy();
  auto t3 = Clock::now();
  double c3 = cpu_now();
  double ins = secs(t2, t3), cins = c3 - c2;
  printf("insert: res %g maxrange %g mode %s%s%s: %.4f s, %.0f points/s, %.0f scans/s (cpu %.4f s, %.0f points/cpu-s)\n", res, maxrange,
         rays ? "insertPointCloudRays" : "insertPointCloud", discretize ? " discretize" : "", lazy ? " lazy" : "",
         ins, npts / ins, scans.size() / ins, cins, npts / cins);
  print_stats("tree", tree);
  if (!outprefix.empty()) {
    auto w0 = Clock::now();
    tree.write(outprefix + ".ot");
    auto w1 = Clock::now();
    tree.writeBinary(outprefix + ".bt");  // converts tree to max-likelihood and prunes first
    auto w2 = Clock::now();
    printf("write: %s.ot %.4f s, %s.bt (toMaxLikelihood+prune+write) %.4f s\n", outprefix.c_str(), secs(w0, w1),
           outprefix.c_str(), secs(w1, w2));
    print_stats("ml-tree", tree);
  }
  return 0;
}

static int cmd_read(int argc, char** argv) {
  std::string fn = argv[2];
  int repeat = 5;
  for (int i = 3; i < argc; ++i)
    if (!strcmp(argv[i], "-repeat")) repeat = atoi(argv[++i]);
  std::vector<double> tr, ti, cr, ci;
  LeafStats st;
  size_t nodes = 0;
  for (int r = 0; r < repeat; ++r) {
    double c0 = cpu_now();
    auto t0 = Clock::now();
    OcTree* t = read_tree(fn);
    auto t1 = Clock::now();
    double c1 = cpu_now();
    if (!t) { fprintf(stderr, "cannot read %s\n", fn.c_str()); return 1; }
    st = leaf_stats(*t);
    auto t2 = Clock::now();
    double c2 = cpu_now();
    nodes = t->size();
    tr.push_back(secs(t0, t1));
    ti.push_back(secs(t1, t2));
    cr.push_back(c1 - c0);
    ci.push_back(c2 - c1);
    delete t;
  }
  std::sort(tr.begin(), tr.end());
  std::sort(ti.begin(), ti.end());
  std::sort(cr.begin(), cr.end());
  std::sort(ci.begin(), ci.end());
  printf("read %s: nodes %zu leaves %zu (occupied %zu, free %zu) | read min %.4f s median %.4f s (cpu min %.4f) | iterate leaves min %.4f s median %.4f s (cpu min %.4f; %.1f Mleaves/s) | leafhash %016" PRIx64 "\n",
         fn.c_str(), nodes, st.leaves, st.occ, st.fr, tr[0], tr[tr.size() / 2], cr[0], ti[0], ti[ti.size() / 2], ci[0],
         st.leaves / ti[0] / 1e6, st.hash);
  return 0;
}

// ---- exact confusion matrix by simultaneous descent ----
enum { OCC = 0, FREE = 1, UNK = 2 };
struct Cmp {
  const OcTree *a, *b;
  uint64_t m[3][3] = {{0}};  // [state in a][state in b], in voxels at depth 16
  unsigned depth_max;
  uint64_t vox(unsigned d) const { return 1ULL << (3 * (depth_max - d)); }
  int st(const OcTree* t, const OcTreeNode* n) const { return n ? (t->isNodeOccupied(n) ? OCC : FREE) : UNK; }
  bool leaf(const OcTree* t, const OcTreeNode* n) const { return !t->nodeHasChildren(n); }
  // one side missing: add the other side's leaves against UNK
  void one(const OcTree* t, const OcTreeNode* n, unsigned d, bool is_a) {
    if (leaf(t, n)) { if (is_a) m[st(t, n)][UNK] += vox(d); else m[UNK][st(t, n)] += vox(d); return; }
    for (unsigned i = 0; i < 8; ++i)
      if (t->nodeChildExists(n, i)) one(t, t->getNodeChild(n, i), d + 1, is_a);
  }
  void both(const OcTreeNode* x, const OcTreeNode* y, unsigned d) {
    bool lx = leaf(a, x), ly = leaf(b, y);
    if (lx && ly) { m[st(a, x)][st(b, y)] += vox(d); return; }
    for (unsigned i = 0; i < 8; ++i) {
      const OcTreeNode* cx = lx ? x : (a->nodeChildExists(x, i) ? a->getNodeChild(x, i) : nullptr);
      const OcTreeNode* cy = ly ? y : (b->nodeChildExists(y, i) ? b->getNodeChild(y, i) : nullptr);
      if (cx && cy) both(cx, cy, d + 1);
      else if (cx) one(a, cx, d + 1, true);
      else if (cy) one(b, cy, d + 1, false);
    }
  }
};

static int cmd_cmp(int argc, char** argv) {
  if (argc < 4) return 2;
  double c0 = cpu_now();
  auto t0 = Clock::now();
  OcTree* a = read_tree(argv[2]);
  OcTree* b = read_tree(argv[3]);
  auto t1 = Clock::now();
  if (!a || !b) { fprintf(stderr, "cannot read inputs\n"); return 1; }
  if (std::abs(a->getResolution() - b->getResolution()) > 1e-9) { fprintf(stderr, "resolution mismatch\n"); return 1; }
  Cmp c;
  c.a = a; c.b = b; c.depth_max = a->getTreeDepth();
  if (a->getRoot() && b->getRoot()) c.both(a->getRoot(), b->getRoot(), 0);
  else if (a->getRoot()) c.one(a, a->getRoot(), 0, true);
  else if (b->getRoot()) c.one(b, b->getRoot(), 0, false);
  auto t2 = Clock::now();
  double c2 = cpu_now();
  const char* nm[3] = {"occ", "free", "unk"};
  printf("cmp %s vs %s: read %.4f s, compare %.4f s (total cpu %.4f s); voxel counts (rows: A, cols: B)\n", argv[2], argv[3], secs(t0, t1), secs(t1, t2), c2 - c0);
  for (int i = 0; i < 3; ++i)
    printf("  A %-4s | B occ %14" PRIu64 " | B free %14" PRIu64 " | B unk %14" PRIu64 "\n", nm[i], c.m[i][0], c.m[i][1], c.m[i][2]);
  uint64_t tp = c.m[OCC][OCC], fp = c.m[FREE][OCC] + c.m[UNK][OCC], fn = c.m[OCC][FREE] + c.m[OCC][UNK];
  printf("  occupied IoU (A as truth) %.6f, known-agreement %.6f\n", tp / double(tp + fp + fn),
         (c.m[OCC][OCC] + c.m[FREE][FREE]) / double(c.m[OCC][OCC] + c.m[FREE][FREE] + c.m[OCC][FREE] + c.m[FREE][OCC]));
  delete a;
  delete b;
  return 0;
}

int main(int argc, char** argv) {
  if (argc >= 3 && !strcmp(argv[1], "insert")) return cmd_insert(argc, argv);
  if (argc >= 3 && !strcmp(argv[1], "read")) return cmd_read(argc, argv);
  if (argc >= 4 && !strcmp(argv[1], "cmp")) return cmd_cmp(argc, argv);
  fprintf(stderr,
          "usage: %s insert <in.graph|in.scans> [-res R] [-m maxrange] [-discretize] [-rays] [-lazy] [-n N] [-o outprefix] [-export-scans f.scans]\n"
          "       %s read <map.bt|map.ot> [-repeat N]\n"
          "       %s cmp <a.bt|a.ot> <b.bt|b.ot>\n",
          argv[0], argv[0], argv[0]);
  return 2;
}
