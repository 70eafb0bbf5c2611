//! Ground truth exported for evaluating clouds: the world description, densely sampled true
//! surface points, and the exact point-to-surface distance.
//!
//! The true surface is the boundary of the union of the world's solid boxes, plus every
//! rectangle (taken whole: rectangles have no volume). Faces or parts of faces that another
//! box covers — the floor under a wall, the bottom of a table leg, the top of a box under the
//! box stacked on it — are not surface: no beam can reach them. [`GroundTruth`] computes that
//! surface once as a list of rectangular [`SurfacePatch`]es: each box face is cut along the
//! edges of every other box into cells, a cell is kept if the space just outside it is free,
//! and kept cells are merged back into rectangles. Distances and samples then come from the
//! patches, exactly (no grid, no tolerance beyond floating point).
//!
//! Every patch, point and sample names its primitive and says whether it is glass, so glass
//! can be scored or shown separately.

use std::path::{Path, PathBuf};

use nalgebra::{Point3, Vector3};
use serde::Serialize;

use scan3d_map::octree::{Key, OctreeError, Resolution, SensorModel, VoxelMap};

use crate::world::{Aabb, Material, Rect, Shape, World};

/// One rectangle of true surface.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfacePatch {
    /// The rectangle (edges perpendicular; box faces are axis-aligned).
    pub rect: Rect,
    /// Index of the primitive it belongs to, in [`World::primitives`] order.
    pub primitive: usize,
    /// Whether the primitive is glass (its returns are random).
    pub glass: bool,
}

impl SurfacePatch {
    /// The area of the patch, square metres.
    pub fn area(&self) -> f64 {
        self.rect.edge_u.norm() * self.rect.edge_v.norm()
    }

    /// Euclidean distance from `p` to the closest point of the patch.
    pub fn distance(&self, p: &Point3<f64>) -> f64 {
        let Rect {
            corner,
            edge_u,
            edge_v,
        } = self.rect;
        let rel = p - corner;
        // The edges are perpendicular, so clamping each coordinate gives the closest point.
        let s = (rel.dot(&edge_u) / edge_u.norm_squared()).clamp(0.0, 1.0);
        let t = (rel.dot(&edge_v) / edge_v.norm_squared()).clamp(0.0, 1.0);
        (rel - edge_u * s - edge_v * t).norm()
    }
}

/// A sampled point of true surface.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfacePoint {
    /// World coordinates, metres.
    pub point: [f64; 3],
    /// Index of the primitive it lies on, in [`World::primitives`] order.
    pub primitive: usize,
    /// Whether that primitive is glass.
    pub glass: bool,
}

/// How close a cloud lies to the true surface.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Accuracy {
    /// Points scored (non-finite points are skipped).
    pub points: usize,
    /// Mean point-to-surface distance, metres.
    pub mean_m: f64,
    /// 95th percentile (nearest rank: the ⌈0.95·n⌉-th smallest distance), metres.
    pub p95_m: f64,
    /// Largest distance, metres.
    pub max_m: f64,
}

/// The true surface of a world, precomputed for fast distance queries and sampling.
#[derive(Debug, Clone, PartialEq)]
pub struct GroundTruth {
    patches: Vec<SurfacePatch>,
}

impl GroundTruth {
    /// The surface of `world` (see the [module docs](self)): visible parts of box faces, merged
    /// into rectangles, then the rectangles, in primitive order. Deterministic.
    pub fn new(world: &World) -> Self {
        let boxes: Vec<Aabb> = world
            .primitives()
            .filter_map(|p| match p.shape {
                Shape::Box(b) => Some(b),
                Shape::Rect(_) => None,
            })
            .collect();
        let mut patches = Vec::new();
        for (index, primitive) in world.primitives().enumerate() {
            let glass = matches!(primitive.material, Material::Glass { .. });
            match primitive.shape {
                Shape::Box(b) => {
                    for rect in visible_faces(&b, &boxes) {
                        patches.push(SurfacePatch {
                            rect,
                            primitive: index,
                            glass,
                        });
                    }
                }
                Shape::Rect(rect) => patches.push(SurfacePatch {
                    rect,
                    primitive: index,
                    glass,
                }),
            }
        }
        Self { patches }
    }

    /// The surface patches.
    pub fn patches(&self) -> &[SurfacePatch] {
        &self.patches
    }

    /// Exact Euclidean distance from `p` to the true surface, metres, from either side (a
    /// point inside a wall is as far as the nearest reachable face). Infinite for a world
    /// without surfaces, NaN for a non-finite point.
    pub fn distance(&self, p: [f64; 3]) -> f64 {
        let p = Point3::from(p);
        self.patches
            .iter()
            .map(|patch| patch.distance(&p))
            .fold(f64::INFINITY, f64::min)
    }

    /// Points on every patch on a regular grid: each patch is cut into ⌈side / spacing⌉ equal
    /// cells per side and sampled at the cell centres, so neighbours on a patch are at most
    /// `spacing_m` apart (and more than `spacing_m / 2` unless the side is shorter). Empty for
    /// a spacing that is not a positive finite number. The count grows as area / spacing².
    pub fn sample(&self, spacing_m: f64) -> Vec<SurfacePoint> {
        if !(spacing_m.is_finite() && spacing_m > 0.0) {
            return Vec::new();
        }
        let cells = |len: f64| ((len / spacing_m).ceil() as usize).max(1);
        let mut out = Vec::new();
        for patch in &self.patches {
            let Rect {
                corner,
                edge_u,
                edge_v,
            } = patch.rect;
            let (nu, nv) = (cells(edge_u.norm()), cells(edge_v.norm()));
            for j in 0..nv {
                let t = (j as f64 + 0.5) / nv as f64;
                for i in 0..nu {
                    let s = (i as f64 + 0.5) / nu as f64;
                    let q = corner + edge_u * s + edge_v * t;
                    out.push(SurfacePoint {
                        point: [q.x, q.y, q.z],
                        primitive: patch.primitive,
                        glass: patch.glass,
                    });
                }
            }
        }
        out
    }

    /// Scores a cloud: mean, 95th percentile and largest point-to-surface distance. `None`
    /// if no point is finite.
    pub fn accuracy(&self, points: impl IntoIterator<Item = [f64; 3]>) -> Option<Accuracy> {
        let mut d: Vec<f64> = points
            .into_iter()
            .filter(|p| p.iter().all(|c| c.is_finite()))
            .map(|p| self.distance(p))
            .collect();
        if d.is_empty() {
            return None;
        }
        d.sort_by(f64::total_cmp);
        let n = d.len();
        let rank = (0.95 * n as f64).ceil() as usize;
        Some(Accuracy {
            points: n,
            mean_m: d.iter().sum::<f64>() / n as f64,
            p95_m: d.get(rank.clamp(1, n) - 1).copied().unwrap_or(f64::NAN),
            max_m: d.last().copied().unwrap_or(f64::NAN),
        })
    }
}

/// The visible parts of the six faces of `b`, as rectangles. A part is visible when the space
/// just outside it is in none of `boxes`.
fn visible_faces(b: &Aabb, boxes: &[Aabb]) -> Vec<Rect> {
    let mut out = Vec::new();
    for k in 0..3 {
        let (ua, va) = ((k + 1) % 3, (k + 2) % 3);
        // In-plane cut lines: the face's own edges and every box edge crossing the face.
        let cuts = |axis: usize| {
            let (lo, hi) = (b.min[axis], b.max[axis]);
            let mut c = vec![lo, hi];
            for other in boxes {
                for x in [other.min[axis], other.max[axis]] {
                    if lo < x && x < hi {
                        c.push(x);
                    }
                }
            }
            c.sort_by(f64::total_cmp);
            c.dedup();
            c
        };
        let (cu, cv) = (cuts(ua), cuts(va));
        for (plane, outward) in [(b.min[k], -1.0), (b.max[k], 1.0)] {
            let probe_k = plane + outward * 1e-9 * plane.abs().max(1.0);
            let free: Vec<Vec<bool>> = cv
                .windows(2)
                .map(|v| {
                    cu.windows(2)
                        .map(|u| {
                            let mut q = Point3::origin();
                            q[k] = probe_k;
                            q[ua] = 0.5 * (u[0] + u[1]);
                            q[va] = 0.5 * (v[0] + v[1]);
                            !boxes.iter().any(|o| o.contains(&q))
                        })
                        .collect()
                })
                .collect();
            for (iu0, iu1, iv0, iv1) in merge_cells(&free) {
                let mut corner = Point3::origin();
                corner[k] = plane;
                corner[ua] = cu[iu0];
                corner[va] = cv[iv0];
                let mut edge_u = Vector3::zeros();
                edge_u[ua] = cu[iu1] - cu[iu0];
                let mut edge_v = Vector3::zeros();
                edge_v[va] = cv[iv1] - cv[iv0];
                out.push(Rect {
                    corner,
                    edge_u,
                    edge_v,
                });
            }
        }
    }
    out
}

/// Merges the `true` cells of a grid (`rows[v][u]`) into rectangles of whole cells, as cut-line
/// index ranges `(u0, u1, v0, v1)`: runs along each row, then identical runs of consecutive
/// rows joined. Deterministic order.
fn merge_cells(rows: &[Vec<bool>]) -> Vec<(usize, usize, usize, usize)> {
    let mut done = Vec::new();
    // Open rectangles: (u0, u1, v0), extended while the next row has the same run.
    let mut open: Vec<(usize, usize, usize)> = Vec::new();
    for (v, row) in rows.iter().enumerate() {
        let mut runs = Vec::new();
        let mut start = None;
        for (u, &cell) in row.iter().chain([&false]).enumerate() {
            match (cell, start) {
                (true, None) => start = Some(u),
                (false, Some(s)) => {
                    runs.push((s, u));
                    start = None;
                }
                _ => {}
            }
        }
        let mut next = Vec::with_capacity(runs.len());
        for (u0, u1) in runs {
            let v0 = open
                .iter()
                .find(|&&(a, b, _)| (a, b) == (u0, u1))
                .map_or(v, |&(_, _, v0)| v0);
            next.push((u0, u1, v0));
        }
        for &(u0, u1, v0) in &open {
            if !next.iter().any(|&(a, b, _)| (a, b) == (u0, u1)) {
                done.push((u0, u1, v0, v));
            }
        }
        open = next;
    }
    done.extend(
        open.into_iter()
            .map(|(u0, u1, v0)| (u0, u1, v0, rows.len())),
    );
    done
}

/// Points sampled on the true surface of `world` about `spacing_m` apart (glass included; use
/// [`GroundTruth::sample`] for the primitive and glass flag of each point).
pub fn surface_points(world: &World, spacing_m: f64) -> Vec<[f64; 3]> {
    GroundTruth::new(world)
        .sample(spacing_m)
        .into_iter()
        .map(|s| s.point)
        .collect()
}

/// Exact distance from `p` to the true surface of `world` (see [`GroundTruth::distance`]).
/// It builds the surface on every call: for many points build a [`GroundTruth`] once.
pub fn distance_to_surface(world: &World, p: [f64; 3]) -> f64 {
    GroundTruth::new(world).distance(p)
}

/// Why the world description could not be exported.
#[derive(Debug, thiserror::Error)]
pub enum TruthError {
    /// The world could not be put into TOML.
    #[error("cannot serialize the world description: {0}")]
    Serialize(#[from] toml::ser::Error),
    /// The file could not be written.
    #[error("cannot write {}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
}

/// The world as TOML in the schema [`World::from_toml_str`] reads (see [`crate::world`]), so
/// that loading it gives the same world back (boxes first, then rectangles, each in order).
pub fn world_description_toml(world: &World) -> Result<String, TruthError> {
    let material = |m: Material| match m {
        Material::Opaque => MaterialOut::Opaque,
        Material::Glass { p_return, p_pass } => MaterialOut::Glass { p_return, p_pass },
    };
    let arr = |p: Point3<f64>| [p.x, p.y, p.z];
    let vec = |v: Vector3<f64>| [v.x, v.y, v.z];
    let room = world.room();
    let mut file = WorldOut {
        room: RoomOut {
            min: arr(room.min),
            max: arr(room.max),
        },
        boxes: Vec::new(),
        rects: Vec::new(),
    };
    for p in world.primitives() {
        match p.shape {
            Shape::Box(b) => file.boxes.push(BoxOut {
                name: &p.name,
                min: arr(b.min),
                max: arr(b.max),
                material: material(p.material),
            }),
            Shape::Rect(r) => file.rects.push(RectOut {
                name: &p.name,
                corner: arr(r.corner),
                edge_u: vec(r.edge_u),
                edge_v: vec(r.edge_v),
                material: material(p.material),
            }),
        }
    }
    Ok(format!(
        "# scan3d-hw-sim world description (schema: scan3d_hw_sim::world).\n{}",
        toml::to_string(&file)?
    ))
}

/// Writes [`world_description_toml`] to `path`.
pub fn write_world_description(world: &World, path: impl AsRef<Path>) -> Result<(), TruthError> {
    let path = path.as_ref();
    std::fs::write(path, world_description_toml(world)?).map_err(|source| TruthError::Io {
        path: path.to_owned(),
        source,
    })
}

#[derive(Serialize)]
struct WorldOut<'a> {
    room: RoomOut,
    #[serde(rename = "box", skip_serializing_if = "Vec::is_empty")]
    boxes: Vec<BoxOut<'a>>,
    #[serde(rename = "rect", skip_serializing_if = "Vec::is_empty")]
    rects: Vec<RectOut<'a>>,
}

#[derive(Serialize)]
struct RoomOut {
    min: [f64; 3],
    max: [f64; 3],
}

#[derive(Serialize)]
struct BoxOut<'a> {
    name: &'a str,
    min: [f64; 3],
    max: [f64; 3],
    material: MaterialOut,
}

#[derive(Serialize)]
struct RectOut<'a> {
    name: &'a str,
    corner: [f64; 3],
    edge_u: [f64; 3],
    edge_v: [f64; 3],
    material: MaterialOut,
}

#[derive(Serialize)]
#[serde(rename_all = "snake_case")]
enum MaterialOut {
    Opaque,
    Glass { p_return: f64, p_pass: f64 },
}

/// The ground-truth occupancy map of `world` at `resolution` metres, in OctoMap's key space:
///
/// - **occupied** (clamp max): every voxel a true surface inside the room (its boundary
///   included: the walls' inner faces) passes through, found by sampling each surface patch
///   every `resolution / 4` (so a surface crossing a voxel by less than a quarter voxel at a
///   corner may be missed) — glass included; surfaces beyond the room (the corridor seen
///   through the glass, the hall beyond the door) are not part of the map;
/// - **free** (clamp min): every voxel whose centre is inside the room, not inside a solid box
///   (furniture, glass) and not occupied;
/// - **unknown**: everything else (outside the room: beyond walls, the doorway, the hall).
///
/// Written with [`scan3d_map::octree::Octree::to_bt_bytes`] it is a `.bt` any OctoMap tool
/// opens, comparable voxel by voxel with maps of the same resolution.
pub fn truth_map(
    world: &World,
    truth: &GroundTruth,
    resolution: f64,
) -> Result<VoxelMap, OctreeError> {
    let res = Resolution::new(resolution)?;
    let model = SensorModel::default();
    let mut map = VoxelMap::new(res, model);
    let room = world.room();
    let key_range = |lo: f64, hi: f64| -> Option<(u16, u16)> {
        Some((res.coord_to_key_axis(lo)?, res.coord_to_key_axis(hi)?))
    };
    let (Some((x0, x1)), Some((y0, y1)), Some((z0, z1))) = (
        key_range(room.min.x, room.max.x),
        key_range(room.min.y, room.max.y),
        key_range(room.min.z, room.max.z),
    ) else {
        return Ok(map);
    };
    for kx in x0..=x1 {
        for ky in y0..=y1 {
            for kz in z0..=z1 {
                let key = Key([kx, ky, kz]);
                let [x, y, z] = res.key_to_coord(key);
                if !world.is_inside_solid(&Point3::new(x, y, z)) {
                    map.set_log_odds(key, model.clamp_min);
                }
            }
        }
    }
    for sample in truth.sample(resolution / 4.0) {
        if !room.contains(&Point3::from(sample.point)) {
            continue;
        }
        let p = sample.point.map(|c| c as f32);
        if let Some(key) = res.coord_to_key(p) {
            map.set_log_odds(key, model.clamp_max);
        }
    }
    Ok(map)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::Primitive;

    fn solid(name: &str, min: [f64; 3], max: [f64; 3]) -> Primitive {
        Primitive {
            name: name.to_owned(),
            shape: Shape::Box(Aabb::new(min, max)),
            material: Material::Opaque,
        }
    }

    fn world(primitives: Vec<Primitive>) -> World {
        World::new(Aabb::new([-5.0; 3], [5.0; 3]), primitives).expect("a valid world")
    }

    fn near(got: f64, want: f64) {
        assert!((got - want).abs() < 1e-9, "got {got}, want {want}");
    }

    #[test]
    fn distances_by_hand_in_the_conference_room() {
        let truth = GroundTruth::new(&World::conference_room());
        // Above the table: its top (z = 0.75) is nearer than the ceiling and the walls.
        near(truth.distance([4.0, 3.0, 1.5]), 0.75);
        // Near the west wall.
        near(truth.distance([0.8, 3.0, 1.2]), 0.8);
        // Beside the table top's north-east edge (5.5, 3.8, 0.72–0.75): √(0.3² + 0.3² + 0.15²).
        near(truth.distance([5.8, 4.1, 0.9]), 0.45);
        // Under the table: the floor.
        near(truth.distance([4.0, 3.0, 0.3]), 0.3);
        // Inside the table top: 1 cm below its top face.
        near(truth.distance([4.0, 3.0, 0.74]), 0.01);
        // Inside the floor slab under the south wall: the floor's top face there is covered by
        // the wall, so the nearest surface is the room corner edge (y = 0, z = 0), not the
        // hidden face 1 cm above.
        near(truth.distance([2.0, -0.03, -0.01]), 0.001f64.sqrt());
        // In front of the open door leaf (hinge (8, 1), free edge towards (7.134, 1.5)): the
        // distance to its plane, normal (0.5, 0.866025, 0) normalised.
        let n = (0.5f64.powi(2) + 0.866025f64.powi(2)).sqrt();
        near(
            truth.distance([7.5, 1.5, 1.0]),
            (-0.5 * 0.5 + 0.5 * 0.866025) / n,
        );
        assert_eq!(
            distance_to_surface(&World::default(), [0.0; 3]),
            f64::INFINITY
        );
    }

    #[test]
    fn stacked_boxes_hide_the_covered_faces() {
        // A unit cube with a 0.5 × 0.5 × 0.5 block standing in the middle of its top.
        let w = world(vec![
            solid("base", [0.0; 3], [1.0; 3]),
            solid("block", [0.25, 0.25, 1.0], [0.75, 0.75, 1.5]),
        ]);
        let truth = GroundTruth::new(&w);
        let area = |primitive: usize| -> f64 {
            truth
                .patches()
                .iter()
                .filter(|p| p.primitive == primitive)
                .map(SurfacePatch::area)
                .sum()
        };
        // Base: 6 faces minus the 0.25 m² under the block; block: 4 sides and the top.
        near(area(0), 6.0 - 0.25);
        near(area(1), 4.0 * 0.25 + 0.25);
        // On the base's top, inside the block's footprint, the surface is 0.5 m up (the block's
        // top) or 0.25 m sideways (its sides): the covered face does not count.
        near(truth.distance([0.5, 0.5, 1.0]), 0.25);
        near(truth.distance([0.3, 0.5, 1.01]), 0.05);
        let points = truth.sample(0.05);
        assert!(points.iter().all(|s| {
            let [x, y, z] = s.point;
            !(z == 1.0 && (0.25..=0.75).contains(&x) && (0.25..=0.75).contains(&y))
        }));
    }

    #[test]
    fn sampling_spacing_and_count() {
        let w = world(vec![solid("b", [1.0, 2.0, 3.0], [2.0, 2.5, 3.3])]);
        let points = surface_points(&w, 0.1);
        // 10 × 5 cells on top and bottom, 10 × 3 on the y faces, 5 × 3 on the x faces.
        assert_eq!(points.len(), 2 * (10 * 5 + 10 * 3 + 5 * 3));
        // The top face: cell centres 0.1 apart, 0.05 in from the edges.
        let mut xs: Vec<f64> = points
            .iter()
            .filter(|p| p[2] == 3.3)
            .map(|p| p[0])
            .collect();
        assert_eq!(xs.len(), 50);
        xs.sort_by(f64::total_cmp);
        xs.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
        assert_eq!(xs.len(), 10);
        for (i, x) in xs.iter().enumerate() {
            near(*x, 1.05 + 0.1 * i as f64);
        }
        // A spacing that does not divide the sides: ⌈1 / 0.3⌉ = 4, ⌈0.5 / 0.3⌉ = 2 and
        // ⌈0.3 / 0.3⌉ = 1 cells: 4 × 2 on top and bottom, 4 × 1 and 2 × 1 on the sides.
        let coarse = surface_points(&w, 0.3);
        assert_eq!(coarse.len(), 2 * (8 + 4 + 2));
        assert!(surface_points(&w, 0.0).is_empty());
        assert!(surface_points(&w, f64::NAN).is_empty());
        assert_eq!(surface_points(&w, 0.1), points);
    }

    #[test]
    fn conference_room_samples_lie_on_the_surface_and_flag_the_glass() {
        let room = World::conference_room();
        let truth = GroundTruth::new(&room);
        let samples = truth.sample(0.1);
        assert!(samples.len() > 10_000, "{}", samples.len());
        let boxes: Vec<Aabb> = room
            .primitives()
            .filter_map(|p| match p.shape {
                Shape::Box(b) => Some(b),
                Shape::Rect(_) => None,
            })
            .collect();
        let strictly_inside =
            |b: &Aabb, q: &[f64; 3]| (0..3).all(|i| b.min[i] < q[i] && q[i] < b.max[i]);
        for s in &samples {
            assert!(truth.distance(s.point) < 1e-12, "{s:?}");
            assert!(!boxes.iter().any(|b| strictly_inside(b, &s.point)), "{s:?}");
        }
        // The glass wall (primitive 7) shows only its two large faces, y = 6 and y = 6.02: its
        // ends and edges touch the walls, floor and ceiling.
        let glass: Vec<&SurfacePoint> = samples.iter().filter(|s| s.glass).collect();
        assert_eq!(glass.len(), 2 * 80 * 30);
        assert!(
            glass
                .iter()
                .all(|s| s.primitive == 7 && (s.point[1] == 6.0 || s.point[1] == 6.02))
        );
        // Nothing of the floor hides under the walls: its top inside the room is 8 × 6 m minus
        // the feet of the legs, boxes and chairs standing on it.
        let floor_in_room: f64 = truth
            .patches()
            .iter()
            .filter(|p| p.primitive == 0 && p.rect.corner.z == 0.0)
            .map(|p| {
                let (a, b) = (p.rect.corner, p.rect.corner + p.rect.edge_u + p.rect.edge_v);
                let overlap = |lo: f64, hi: f64, max: f64| (hi.min(max) - lo.max(0.0)).max(0.0);
                overlap(a.x.min(b.x), a.x.max(b.x), 8.0) * overlap(a.y.min(b.y), a.y.max(b.y), 6.0)
            })
            .sum();
        let legs = 4.0 * 0.06 * 0.06;
        let chairs = 4.0 * 0.45 * 0.5;
        let boxes_on_floor = 0.6 * 0.4 + 0.6 * 0.8;
        near(floor_in_room, 48.0 - legs - chairs - boxes_on_floor);
    }

    #[test]
    fn accuracy_mean_and_nearest_rank_percentile() {
        let w = world(vec![solid("slab", [-1.0, -1.0, -1.0], [1.0, 1.0, 0.0])]);
        let truth = GroundTruth::new(&w);
        // 20 points at heights 0.01..0.20 above the slab's top, and one non-finite point.
        let mut points: Vec<[f64; 3]> =
            (1..=20).map(|i| [0.0, 0.0, f64::from(i) / 100.0]).collect();
        points.push([f64::NAN, 0.0, 0.0]);
        let a = truth.accuracy(points).expect("finite points");
        assert_eq!(a.points, 20);
        near(a.mean_m, 0.105);
        near(a.p95_m, 0.19); // ⌈0.95 · 20⌉ = 19th smallest
        near(a.max_m, 0.20);
        assert_eq!(truth.accuracy([[f64::INFINITY; 3]]), None);
    }

    #[test]
    fn world_description_round_trips() {
        let room = World::conference_room();
        let text = world_description_toml(&room).expect("serializable");
        assert!(text.contains("glass"), "{text}");
        assert_eq!(
            World::from_toml_str(&text).map_err(|e| e.to_string()),
            Ok(room.clone())
        );
        let path = std::env::temp_dir().join(format!("scan3d-truth-{}.toml", std::process::id()));
        write_world_description(&room, &path).expect("writable temp dir");
        let loaded = World::load(&path).map_err(|e| e.to_string());
        let _ = std::fs::remove_file(&path);
        assert_eq!(loaded, Ok(room.clone()));
        let bad = write_world_description(&room, "/nonexistent/dir/world.toml")
            .map_err(|e| e.to_string());
        assert!(
            matches!(&bad, Err(m) if m.starts_with("cannot write /nonexistent/dir/world.toml")),
            "{bad:?}"
        );
    }

    #[test]
    fn truth_map_of_a_box_room_by_hand() {
        // A 4 × 3 × 2.5 m room of six 0.1 m slabs, at 0.5 m: 8 × 6 × 5 voxel centres inside.
        let slab = |name: &str, min: [f64; 3], max: [f64; 3]| solid(name, min, max);
        let world = World::new(
            Aabb::new([0.0, 0.0, 0.0], [4.0, 3.0, 2.5]),
            vec![
                slab("floor", [-0.1, -0.1, -0.1], [4.1, 3.1, 0.0]),
                slab("ceiling", [-0.1, -0.1, 2.5], [4.1, 3.1, 2.6]),
                slab("west", [-0.1, -0.1, 0.0], [0.0, 3.1, 2.5]),
                slab("east", [4.0, -0.1, 0.0], [4.1, 3.1, 2.5]),
                slab("south", [-0.1, -0.1, 0.0], [4.1, 0.0, 2.5]),
                slab("north", [-0.1, 3.0, 0.0], [4.1, 3.1, 2.5]),
            ],
        )
        .expect("a valid world");
        let truth = GroundTruth::new(&world);
        let map = truth_map(&world, &truth, 0.5).expect("truth map");
        let res = Resolution::new(0.5).expect("resolution");
        let model = SensorModel::default();
        let (mut occupied, mut free) = (0, 0);
        let k = |c: f64| res.coord_to_key_axis(c).expect("in range");
        for x in k(-1.0)..=k(5.0) {
            for y in k(-1.0)..=k(4.0) {
                for z in k(-1.0)..=k(3.5) {
                    match map.log_odds(Key([x, y, z])) {
                        Some(v) if v == model.clamp_max => occupied += 1,
                        Some(v) if v == model.clamp_min => free += 1,
                        Some(v) => panic!("unexpected value {v}"),
                        None => {}
                    }
                }
            }
        }
        // Faces at x = 0, y = 0, z = 0 fall in the first inner layer (a point on a voxel
        // boundary belongs to the upper voxel, as in OctoMap): 30 + 40 + 48 − 5 − 6 − 8 + 1 =
        // 100 inner voxels. The faces at x = 4, y = 3, z = 2.5 fall just outside: 30 + 40 + 48.
        assert_eq!(occupied, 100 + 118);
        assert_eq!(free, 8 * 6 * 5 - 100);
    }
}
