//! The simulated world: a room made of primitives with materials, ray intersection, and
//! ground truth for the map evaluation.
//!
//! A [`World`] is the interior box of the room (the volume the map should cover) plus a list of
//! [`Primitive`]s: solid axis-aligned boxes (walls, floor, ceiling, furniture) and thin
//! oriented rectangles (an open door leaf). Each primitive has a [`Material`]: opaque surfaces
//! always return the beam; glass decides per ray whether it reflects, lets the beam through
//! to whatever is behind it, or swallows it.
//!
//! Frame: metres, origin at a floor corner of the room, x along the long (8 m) side, y along
//! the short (6 m) side, z up.
//!
//! # TOML schema
//!
//! ```toml
//! # The room interior: ground truth counts everything outside it as solid.
//! [room]
//! min = [0.0, 0.0, 0.0]
//! max = [8.0, 6.0, 3.0]
//!
//! # A solid axis-aligned box (any number of these). `min` < `max` on every axis.
//! [[box]]
//! name = "floor"
//! min = [-0.1, -0.1, -0.1]
//! max = [8.1, 8.1, 0.0]
//! material = "opaque"            # optional, "opaque" is the default
//!
//! [[box]]
//! name = "glass_wall"
//! min = [0.0, 6.0, 0.0]
//! max = [8.0, 6.02, 3.0]
//! # per ray: reflect with p_return, pass through with p_pass, else no return
//! material = { glass = { p_return = 0.3, p_pass = 0.5 } }
//!
//! # A thin rectangle: corner + s·edge_u + t·edge_v for s, t in [0, 1]. The edges must be
//! # perpendicular and non-zero.
//! [[rect]]
//! name = "door_leaf"
//! corner = [8.0, 1.0, 0.0]
//! edge_u = [-0.866025, 0.5, 0.0]
//! edge_v = [0.0, 0.0, 2.1]
//! ```
//!
//! `hw-sim/worlds/conference_room.toml` is the full default room; it loads to exactly
//! [`World::conference_room`]. In a loaded world, boxes come first (in file order), then
//! rectangles.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::{Isometry3, Point3, Unit, Vector3};
use rand::Rng;
use serde::Deserialize;

use crate::noise::RangeNoise;

/// An axis-aligned box, `min` ≤ `max` on every axis (closed: the faces belong to the box).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Aabb {
    /// The corner with the smallest coordinates.
    pub min: Point3<f64>,
    /// The corner with the largest coordinates.
    pub max: Point3<f64>,
}

impl Aabb {
    /// The box spanned by two corners given as `[x, y, z]` arrays.
    pub fn new(min: [f64; 3], max: [f64; 3]) -> Self {
        Self {
            min: Point3::from(min),
            max: Point3::from(max),
        }
    }

    /// Whether `p` lies in the box or on its faces.
    pub fn contains(&self, p: &Point3<f64>) -> bool {
        (0..3).all(|i| self.min[i] <= p[i] && p[i] <= self.max[i])
    }

    /// The smallest box containing both `self` and `other`.
    pub fn union(&self, other: &Aabb) -> Aabb {
        Aabb {
            min: self.min.inf(&other.min),
            max: self.max.sup(&other.max),
        }
    }

    /// Slab method: the parameter interval `[t_enter, t_exit]` over which the line
    /// `origin + t·dir` lies in the box, or `None` if it misses. A ray parallel to a pair of
    /// faces hits only if its origin lies between them (faces included: grazing counts).
    pub fn ray_interval(&self, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<(f64, f64)> {
        let mut t_enter = f64::NEG_INFINITY;
        let mut t_exit = f64::INFINITY;
        for i in 0..3 {
            let (lo, hi, o, d) = (self.min[i], self.max[i], origin[i], dir[i]);
            if d == 0.0 {
                if o < lo || o > hi {
                    return None;
                }
            } else {
                let (a, b) = ((lo - o) / d, (hi - o) / d);
                t_enter = t_enter.max(a.min(b));
                t_exit = t_exit.min(a.max(b));
            }
        }
        (t_enter <= t_exit).then_some((t_enter, t_exit))
    }

    /// Distance along the ray (`dir` of unit length) to where it first touches the solid box:
    /// the entry face from outside, `0` if the origin is already inside.
    pub fn ray_hit(&self, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<f64> {
        let (t_enter, t_exit) = self.ray_interval(origin, dir)?;
        (t_exit >= 0.0).then_some(t_enter.max(0.0))
    }
}

/// A thin planar rectangle: the points `corner + s·edge_u + t·edge_v`, `s, t ∈ [0, 1]`, with
/// perpendicular edges. It has no volume (an open door leaf, a sheet).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rect {
    /// One corner.
    pub corner: Point3<f64>,
    /// The first edge from `corner`.
    pub edge_u: Vector3<f64>,
    /// The second edge from `corner`, perpendicular to `edge_u`.
    pub edge_v: Vector3<f64>,
}

impl Rect {
    /// Distance along the ray (`dir` of unit length) to the rectangle, if it hits from either
    /// side. Rays in the rectangle's plane miss.
    pub fn ray_hit(&self, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<f64> {
        let normal = self.edge_u.cross(&self.edge_v);
        let denom = dir.dot(&normal);
        if denom.abs() <= 1e-12 * normal.norm() {
            return None;
        }
        let t = (self.corner - origin).dot(&normal) / denom;
        if t.is_nan() || t < 0.0 {
            return None;
        }
        let rel = origin + dir * t - self.corner;
        let s = rel.dot(&self.edge_u) / self.edge_u.norm_squared();
        let r = rel.dot(&self.edge_v) / self.edge_v.norm_squared();
        ((0.0..=1.0).contains(&s) && (0.0..=1.0).contains(&r)).then_some(t)
    }

    /// The four corners.
    pub fn corners(&self) -> [Point3<f64>; 4] {
        let c = self.corner;
        [
            c,
            c + self.edge_u,
            c + self.edge_v,
            c + self.edge_u + self.edge_v,
        ]
    }
}

/// The geometry of a [`Primitive`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    /// A solid axis-aligned box.
    Box(Aabb),
    /// A thin oriented rectangle.
    Rect(Rect),
}

impl Shape {
    /// Distance along a unit-direction ray to the first point of the shape, if any.
    pub fn ray_hit(&self, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<f64> {
        match self {
            Shape::Box(b) => b.ray_hit(origin, dir),
            Shape::Rect(r) => r.ray_hit(origin, dir),
        }
    }

    /// The axis-aligned bounding box of the shape.
    pub fn bounds(&self) -> Aabb {
        match self {
            Shape::Box(b) => *b,
            Shape::Rect(r) => {
                let [a, b, c, d] = r.corners();
                Aabb {
                    min: a.inf(&b).inf(&c).inf(&d),
                    max: a.sup(&b).sup(&c).sup(&d),
                }
            }
        }
    }
}

/// How a surface answers a lidar beam.
///
/// In TOML: `material = "opaque"` or `material = { glass = { p_return = 0.3, p_pass = 0.5 } }`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Material {
    /// Always returns the beam at the surface.
    #[default]
    Opaque,
    /// Decided afresh for every ray that reaches it: with probability `p_return` the beam is
    /// reflected (the glass distance is measured), with `p_pass` it goes through and may hit
    /// what is behind, and with the rest (`1 − p_return − p_pass`) it is lost (no return).
    Glass {
        /// Probability of a return from the glass itself.
        p_return: f64,
        /// Probability that the beam passes through.
        p_pass: f64,
    },
}

/// One named piece of the world.
#[derive(Debug, Clone, PartialEq)]
pub struct Primitive {
    /// A name for error messages and ground-truth reports ("table_top").
    pub name: String,
    /// Its geometry.
    pub shape: Shape,
    /// How it answers the beam.
    pub material: Material,
}

/// Why a world description was rejected.
#[derive(Debug, thiserror::Error)]
pub enum WorldError {
    /// The file could not be read.
    #[error("cannot read world file {}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The text is not valid TOML or does not fit the schema (the message names the line,
    /// column and field).
    #[error("{0}")]
    Toml(#[from] toml::de::Error),
    /// A value fits the schema but makes no sense (an inverted box, a probability above 1).
    #[error("{location}: {reason}")]
    Invalid {
        /// Where: the line and primitive (`line 12, box "table_top"`) or just the primitive.
        location: String,
        /// What is wrong with it.
        reason: String,
    },
    /// An error in a world file, with the file named.
    #[error("{}: {source}", path.display())]
    InFile {
        /// The file.
        path: PathBuf,
        /// The error inside it.
        source: Box<WorldError>,
    },
}

/// The simulated environment: the room interior and the primitives that reflect the beams.
///
/// `World::default()` is empty: no surfaces (every ray misses) and a degenerate room.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct World {
    room: Aabb,
    primitives: Vec<Primitive>,
}

/// Probability that the default room's glass wall reflects a beam.
pub const GLASS_P_RETURN: f64 = 0.3;
/// Probability that a beam passes through the default room's glass wall.
pub const GLASS_P_PASS: f64 = 0.5;

impl World {
    /// A closed, opaque room with its interior `[0, size]` (walls, floor and ceiling 0.1 m slabs)
    /// and `inside` added: every return is exact, for tests that check ranges by hand.
    pub fn shell(size: [f64; 3], inside: Vec<Primitive>) -> Result<Self, WorldError> {
        let [x, y, z] = size;
        let slab = |name: &str, min: [f64; 3], max: [f64; 3]| Primitive {
            name: name.to_owned(),
            shape: Shape::Box(Aabb::new(min, max)),
            material: Material::Opaque,
        };
        let mut primitives = vec![
            slab("floor", [-0.1, -0.1, -0.1], [x + 0.1, y + 0.1, 0.0]),
            slab("ceiling", [-0.1, -0.1, z], [x + 0.1, y + 0.1, z + 0.1]),
            slab("south", [-0.1, -0.1, 0.0], [x + 0.1, 0.0, z]),
            slab("north", [-0.1, y, 0.0], [x + 0.1, y + 0.1, z]),
            slab("west", [-0.1, -0.1, 0.0], [0.0, y + 0.1, z]),
            slab("east", [x, -0.1, 0.0], [x + 0.1, y + 0.1, z]),
        ];
        primitives.extend(inside);
        World::new(Aabb::new([0.0; 3], size), primitives)
    }

    /// A world from its room interior and primitives, after checking them (see
    /// [`WorldError::Invalid`]).
    pub fn new(room: Aabb, primitives: Vec<Primitive>) -> Result<Self, WorldError> {
        check_box("room", &room)?;
        for (i, p) in primitives.iter().enumerate() {
            let kind = match p.shape {
                Shape::Box(_) => "box",
                Shape::Rect(_) => "rect",
            };
            check_primitive(p).map_err(|reason| WorldError::Invalid {
                location: format!("{kind} #{} \"{}\"", i + 1, p.name),
                reason,
            })?;
        }
        Ok(Self { room, primitives })
    }

    /// The default room: 8 × 6 × 3 m, origin at a floor corner.
    ///
    /// - Walls, floor and ceiling are 0.1 m solid slabs outside the interior.
    /// - The north long wall (y = 6) is a 2 cm glass pane (p_return [`GLASS_P_RETURN`],
    ///   p_pass [`GLASS_P_PASS`]); behind it a 2 m corridor ends at an opaque wall at y = 8.
    /// - The east wall (x = 8) has a doorway, y ∈ [1, 2], z ∈ [0, 2.1]. The door leaf is hinged
    ///   at (8, 1) and opened 60° into the room, so its free edge is at (7.134, 1.5). Beyond
    ///   the doorway is a hall: floor out to x = 10 and a wall at x = 10 (no hall ceiling, so
    ///   steep rays through the door get no return).
    /// - A 3 × 1.6 m table (top at 0.72–0.75 m, four legs) in the middle, four chairs (seat
    ///   block + backrest), and stacked boxes in the south-west corner plus one by the glass.
    pub fn conference_room() -> Self {
        let glass = Material::Glass {
            p_return: GLASS_P_RETURN,
            p_pass: GLASS_P_PASS,
        };
        let b = |name: &str, min: [f64; 3], max: [f64; 3]| Primitive {
            name: name.to_owned(),
            shape: Shape::Box(Aabb::new(min, max)),
            material: Material::Opaque,
        };
        let mut glass_wall = b("glass_wall", [0.0, 6.0, 0.0], [8.0, 6.02, 3.0]);
        glass_wall.material = glass;
        let primitives = vec![
            // Shell.
            b("floor", [-0.1, -0.1, -0.1], [8.1, 8.1, 0.0]),
            b("ceiling", [-0.1, -0.1, 3.0], [8.1, 8.1, 3.1]),
            b("south_wall", [-0.1, -0.1, 0.0], [8.1, 0.0, 3.0]),
            b("west_wall", [-0.1, -0.1, 0.0], [0.0, 8.1, 3.0]),
            b("east_wall_south", [8.0, -0.1, 0.0], [8.1, 1.0, 3.0]),
            b("east_wall_north", [8.0, 2.0, 0.0], [8.1, 8.1, 3.0]),
            b("east_wall_lintel", [8.0, 1.0, 2.1], [8.1, 2.0, 3.0]),
            glass_wall,
            b("corridor_wall", [-0.1, 8.0, 0.0], [8.1, 8.1, 3.0]),
            b("hall_floor", [8.1, -1.0, -0.1], [10.0, 4.0, 0.0]),
            b("hall_wall", [10.0, -1.0, -0.1], [10.1, 4.0, 3.0]),
            // Table.
            b("table_top", [2.5, 2.2, 0.72], [5.5, 3.8, 0.75]),
            b("table_leg_sw", [2.6, 2.3, 0.0], [2.66, 2.36, 0.72]),
            b("table_leg_se", [5.34, 2.3, 0.0], [5.4, 2.36, 0.72]),
            b("table_leg_nw", [2.6, 3.64, 0.0], [2.66, 3.7, 0.72]),
            b("table_leg_ne", [5.34, 3.64, 0.0], [5.4, 3.7, 0.72]),
            // Chairs: seat block and backrest, backs away from the table.
            b("chair_1_seat", [3.0, 1.55, 0.0], [3.45, 2.0, 0.45]),
            b("chair_1_back", [3.0, 1.5, 0.0], [3.45, 1.55, 0.9]),
            b("chair_2_seat", [4.5, 1.55, 0.0], [4.95, 2.0, 0.45]),
            b("chair_2_back", [4.5, 1.5, 0.0], [4.95, 1.55, 0.9]),
            b("chair_3_seat", [3.0, 4.0, 0.0], [3.45, 4.45, 0.45]),
            b("chair_3_back", [3.0, 4.45, 0.0], [3.45, 4.5, 0.9]),
            b("chair_4_seat", [4.5, 4.0, 0.0], [4.95, 4.45, 0.45]),
            b("chair_4_back", [4.5, 4.45, 0.0], [4.95, 4.5, 0.9]),
            // Boxes on the floor.
            b("box_1", [0.3, 0.3, 0.0], [0.9, 0.7, 0.5]),
            b("box_2", [0.35, 0.35, 0.5], [0.75, 0.65, 0.8]),
            b("box_3", [6.8, 4.8, 0.0], [7.4, 5.6, 0.6]),
            // Door leaf (rectangles come after boxes, as in a loaded file).
            Primitive {
                name: "door_leaf".to_owned(),
                shape: Shape::Rect(Rect {
                    corner: Point3::new(8.0, 1.0, 0.0),
                    edge_u: Vector3::new(-0.866025, 0.5, 0.0),
                    edge_v: Vector3::new(0.0, 0.0, 2.1),
                }),
                material: Material::Opaque,
            },
        ];
        Self {
            room: Aabb::new([0.0, 0.0, 0.0], [8.0, 6.0, 3.0]),
            primitives,
        }
    }

    /// Parses a world from TOML (schema in the [module docs](self)).
    pub fn from_toml_str(text: &str) -> Result<Self, WorldError> {
        let spec: WorldSpec = toml::from_str(text)?;
        let line_of = |span: std::ops::Range<usize>| {
            text.get(..span.start)
                .map_or(0, |head| head.matches('\n').count())
                + 1
        };
        let room = Aabb::new(spec.room.min, spec.room.max);
        check_box("room", &room)?;
        let mut primitives = Vec::with_capacity(spec.boxes.len() + spec.rects.len());
        for entry in spec.boxes {
            let line = line_of(entry.span());
            let BoxSpec {
                name,
                min,
                max,
                material,
            } = entry.into_inner();
            primitives.push((line, "box", name, Shape::Box(Aabb::new(min, max)), material));
        }
        for entry in spec.rects {
            let line = line_of(entry.span());
            let RectSpec {
                name,
                corner,
                edge_u,
                edge_v,
                material,
            } = entry.into_inner();
            let rect = Rect {
                corner: Point3::from(corner),
                edge_u: Vector3::from(edge_u),
                edge_v: Vector3::from(edge_v),
            };
            primitives.push((line, "rect", name, Shape::Rect(rect), material));
        }
        let primitives = primitives
            .into_iter()
            .map(|(line, kind, name, shape, material)| {
                let p = Primitive {
                    name,
                    shape,
                    material,
                };
                check_primitive(&p).map_err(|reason| WorldError::Invalid {
                    location: format!("line {line}, {kind} \"{}\"", p.name),
                    reason,
                })?;
                Ok(p)
            })
            .collect::<Result<Vec<_>, WorldError>>()?;
        Ok(Self { room, primitives })
    }

    /// Reads and parses a world file; errors name the file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, WorldError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|source| WorldError::Io {
            path: path.to_owned(),
            source,
        })?;
        Self::from_toml_str(&text).map_err(|e| WorldError::InFile {
            path: path.to_owned(),
            source: Box::new(e),
        })
    }

    /// The room interior: the volume a map of this world should cover.
    pub fn room(&self) -> Aabb {
        self.room
    }

    /// All primitives, boxes first, in definition order.
    pub fn primitives(&self) -> std::slice::Iter<'_, Primitive> {
        self.primitives.iter()
    }

    /// The box around the room and every primitive (including what lies beyond the glass and
    /// the doorway).
    pub fn bounds(&self) -> Aabb {
        self.primitives
            .iter()
            .fold(self.room, |acc, p| acc.union(&p.shape.bounds()))
    }

    /// Ground truth occupancy: `true` outside the room interior (walls, the doorway, the
    /// corridor and hall count as solid: the map covers the room only) or inside any box
    /// primitive (furniture, glass). Faces count as inside; rectangles have no volume.
    pub fn is_inside_solid(&self, point: &Point3<f64>) -> bool {
        !self.room.contains(point)
            || self.primitives.iter().any(|p| match &p.shape {
                Shape::Box(b) => b.contains(point),
                Shape::Rect(_) => false,
            })
    }

    /// Distance along the ray to the first surface that returns the beam, if any within
    /// `max_range_m`. Glass returns are random (pass through or reflect), drawn from `rng`.
    ///
    /// Surfaces are visited nearest first; each glass surface reached draws one uniform number.
    /// A ray starting inside a solid box hits it at distance 0.
    pub fn cast<R: Rng + ?Sized>(
        &self,
        origin: &Point3<f64>,
        dir: &Unit<Vector3<f64>>,
        max_range_m: f64,
        rng: &mut R,
    ) -> Option<f64> {
        if !(origin.coords.iter().all(|c| c.is_finite()) && max_range_m >= 0.0) {
            return None;
        }
        let mut hits: Vec<(f64, Material)> = self
            .primitives
            .iter()
            .filter_map(|p| {
                let t = p.shape.ray_hit(origin, dir)?;
                (t <= max_range_m).then_some((t, p.material))
            })
            .collect();
        hits.sort_by(|a, b| a.0.total_cmp(&b.0));
        for (t, material) in hits {
            match material {
                Material::Opaque => return Some(t),
                Material::Glass { p_return, p_pass } => {
                    let u: f64 = rng.random();
                    if u < p_return {
                        return Some(t);
                    }
                    if u >= p_return + p_pass {
                        return None;
                    }
                }
            }
        }
        None
    }
}

/// Checks a box has finite corners and positive extent on every axis.
fn check_box(what: &str, b: &Aabb) -> Result<(), WorldError> {
    check_aabb(b).map_err(|reason| WorldError::Invalid {
        location: what.to_owned(),
        reason,
    })
}

fn check_aabb(b: &Aabb) -> Result<(), String> {
    for (i, axis) in ["x", "y", "z"].iter().enumerate() {
        let (lo, hi) = (b.min[i], b.max[i]);
        if !(lo.is_finite() && hi.is_finite()) {
            return Err(format!("min.{axis} and max.{axis} must be finite numbers"));
        }
        if lo >= hi {
            return Err(format!(
                "min.{axis} ({lo}) must be less than max.{axis} ({hi})"
            ));
        }
    }
    Ok(())
}

fn check_primitive(p: &Primitive) -> Result<(), String> {
    match &p.shape {
        Shape::Box(b) => check_aabb(b)?,
        Shape::Rect(r) => {
            let finite = |v: &[f64]| v.iter().all(|c| c.is_finite());
            if !(finite(r.corner.coords.as_slice())
                && finite(r.edge_u.as_slice())
                && finite(r.edge_v.as_slice()))
            {
                return Err("corner, edge_u and edge_v must be finite numbers".to_owned());
            }
            let (nu, nv) = (r.edge_u.norm(), r.edge_v.norm());
            if nu == 0.0 || nv == 0.0 {
                return Err("edge_u and edge_v must be non-zero".to_owned());
            }
            if r.edge_u.dot(&r.edge_v).abs() > 1e-6 * nu * nv {
                return Err("edge_u and edge_v must be perpendicular".to_owned());
            }
        }
    }
    if let Material::Glass { p_return, p_pass } = p.material {
        let prob = |x: f64| (0.0..=1.0).contains(&x);
        if !(prob(p_return) && prob(p_pass)) {
            return Err(format!(
                "glass p_return ({p_return}) and p_pass ({p_pass}) must be in [0, 1]"
            ));
        }
        if p_return + p_pass > 1.0 + 1e-12 {
            return Err(format!(
                "glass p_return + p_pass ({}) must not exceed 1",
                p_return + p_pass
            ));
        }
    }
    Ok(())
}

/// The TOML file layout.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct WorldSpec {
    room: RoomSpec,
    #[serde(default, rename = "box")]
    boxes: Vec<toml::Spanned<BoxSpec>>,
    #[serde(default, rename = "rect")]
    rects: Vec<toml::Spanned<RectSpec>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RoomSpec {
    min: [f64; 3],
    max: [f64; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BoxSpec {
    name: String,
    min: [f64; 3],
    max: [f64; 3],
    #[serde(default)]
    material: Material,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RectSpec {
    name: String,
    corner: [f64; 3],
    edge_u: [f64; 3],
    edge_v: [f64; 3],
    #[serde(default)]
    material: Material,
}

/// Where a sensor is (sensor frame → world frame) at simulated time `t_ns`: a fixed pose
/// ([`Isometry3`] itself) or one that follows a mechanism such as
/// [`crate::turntable::TurntableMount`].
pub trait PoseSource: std::fmt::Debug + Send + Sync {
    /// The sensor pose at simulated time `t_ns`.
    fn pose_at(&self, t_ns: u64) -> Isometry3<f64>;
}

/// A sensor that never moves.
impl PoseSource for Isometry3<f64> {
    fn pose_at(&self, _t_ns: u64) -> Isometry3<f64> {
        *self
    }
}

/// A 2D lidar placed in the world: what one beam at a given azimuth measures.
#[derive(Debug, Clone)]
pub struct Scanner {
    /// The world the beam travels in.
    pub world: Arc<World>,
    /// Sensor frame → world frame. In the sensor frame the beam at azimuth α (radians,
    /// counter-clockwise about +z) points along (cos α, sin α, 0).
    pub pose: Isometry3<f64>,
    /// Range noise added to true ranges.
    pub noise: RangeNoise,
    /// Shortest range the sensor reports, metres (closer → no return).
    pub min_range_m: f64,
    /// Longest range the sensor reports, metres (farther → no return).
    pub max_range_m: f64,
}

impl Scanner {
    /// Noisy range measured at azimuth `azimuth_rad` (sensor frame, counter-clockwise),
    /// or `None` for no return.
    pub fn measure<R: Rng + ?Sized>(&self, azimuth_rad: f64, rng: &mut R) -> Option<f64> {
        self.measure_from(&self.pose, azimuth_rad, rng)
    }

    /// Like [`Scanner::measure`], but from `pose` instead of [`Scanner::pose`]: for a sensor
    /// that moves (a Sweep on a turntable, see [`PoseSource`]).
    pub fn measure_from<R: Rng + ?Sized>(
        &self,
        pose: &Isometry3<f64>,
        azimuth_rad: f64,
        rng: &mut R,
    ) -> Option<f64> {
        let dir = Unit::new_normalize(
            pose.rotation * Vector3::new(azimuth_rad.cos(), azimuth_rad.sin(), 0.0),
        );
        let origin = Point3::from(pose.translation.vector);
        let range = self.world.cast(&origin, &dir, self.max_range_m, rng)?;
        let noisy = self.noise.apply(range, rng);
        (noisy >= self.min_range_m && noisy <= self.max_range_m).then_some(noisy)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    const EPS: f64 = 1e-9;

    fn cast(world: &World, from: [f64; 3], dir: [f64; 3]) -> Option<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let dir = Unit::new_normalize(Vector3::from(dir));
        world.cast(&Point3::from(from), &dir, 100.0, &mut rng)
    }

    fn assert_near(got: Option<f64>, want: f64) {
        match got {
            Some(g) => assert!((g - want).abs() < EPS, "got {g}, want {want}"),
            None => panic!("no return, want {want}"),
        }
    }

    #[test]
    fn axis_aligned_rays_hit_walls_floor_ceiling_and_furniture() {
        let w = World::conference_room();
        let p = [3.2, 0.5, 0.6];
        assert_near(cast(&w, p, [1.0, 0.0, 0.0]), 8.0 - 3.2); // east wall
        assert_near(cast(&w, p, [-1.0, 0.0, 0.0]), 3.2 - 0.75); // box_2 (stacked) face
        assert_near(cast(&w, p, [0.0, -1.0, 0.0]), 0.5); // south wall
        assert_near(cast(&w, p, [0.0, 1.0, 0.0]), 1.5 - 0.5); // chair_1 backrest
        assert_near(cast(&w, p, [0.0, 0.0, 1.0]), 3.0 - 0.6); // ceiling
        assert_near(cast(&w, p, [0.0, 0.0, -1.0]), 0.6); // floor
        // Table top from above and from below.
        assert_near(cast(&w, [4.0, 3.0, 1.5], [0.0, 0.0, -1.0]), 1.5 - 0.75);
        assert_near(cast(&w, [4.0, 3.0, 0.3], [0.0, 0.0, 1.0]), 0.72 - 0.3);
        // West wall at y = 3 (nothing in between at z = 1.5).
        assert_near(cast(&w, [4.0, 3.0, 1.5], [-1.0, 0.0, 0.0]), 4.0);
    }

    #[test]
    fn diagonal_ray_hits_a_corner_region_exactly() {
        let w = World::conference_room();
        // From (4, 3, 1.5) down at 45° in x-z: the table top (z = 0.75, x up to 5.5) is met at
        // x = 4.75, after 0.75 · √2.
        assert_near(
            cast(&w, [4.0, 3.0, 1.5], [1.0, 0.0, -1.0]),
            0.75 * 2f64.sqrt(),
        );
    }

    #[test]
    fn rays_through_the_doorway_reach_the_hall() {
        let w = World::conference_room();
        // y = 1.8 is in the doorway (1..2) and beyond the open leaf's free edge (y ≤ 1.5).
        assert_near(cast(&w, [5.0, 1.8, 1.0], [1.0, 0.0, 0.0]), 10.0 - 5.0);
        // Next to the doorway the wall answers.
        assert_near(cast(&w, [5.0, 2.5, 1.0], [1.0, 0.0, 0.0]), 8.0 - 5.0);
        // Above the door: the lintel.
        assert_near(cast(&w, [5.0, 1.8, 2.5], [1.0, 0.0, 0.0]), 8.0 - 5.0);
        // y = 1.25 meets the open leaf halfway along it: x = 8 − 0.866025 / 2.
        assert_near(
            cast(&w, [5.0, 1.25, 1.0], [1.0, 0.0, 0.0]),
            8.0 - 0.4330125 - 5.0,
        );
        // Steeply up through the doorway: no hall ceiling, no return.
        assert_eq!(cast(&w, [7.9, 1.5, 1.9], [1.0, 0.0, 1.0]), None);
    }

    #[test]
    fn rays_from_outside_and_inside_boxes() {
        let w = World::conference_room();
        // From the corridor, back through the glass is random; along the corridor is not.
        assert_near(cast(&w, [4.0, 7.0, 1.0], [1.0, 0.0, 0.0]), 8.1 - 4.0 - 0.1);
        // From inside the table top: distance 0.
        assert_near(cast(&w, [4.0, 3.0, 0.73], [1.0, 0.0, 0.0]), 0.0);
        // From outside the building towards it: the west wall's outer face.
        assert_near(cast(&w, [-2.0, 3.0, 1.0], [1.0, 0.0, 0.0]), 1.9);
        // Away from the building: nothing.
        assert_eq!(cast(&w, [-2.0, 3.0, 1.0], [-1.0, 0.0, 0.0]), None);
        // Max range cuts off.
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let dir = Unit::new_normalize(Vector3::new(1.0, 0.0, 0.0));
        assert_eq!(
            w.cast(&Point3::new(4.0, 3.0, 1.5), &dir, 3.9, &mut rng),
            None
        );
        assert_eq!(
            w.cast(&Point3::new(f64::NAN, 3.0, 1.5), &dir, 30.0, &mut rng),
            None
        );
    }

    #[test]
    fn glass_reflects_passes_or_loses_at_the_configured_rates() {
        let w = World::conference_room();
        let mut rng = ChaCha8Rng::seed_from_u64(42);
        let dir = Unit::new_normalize(Vector3::new(0.0, 1.0, 0.0));
        let origin = Point3::new(4.0, 5.0, 1.5);
        let n = 20_000;
        let (mut glass, mut corridor, mut lost) = (0, 0, 0);
        for _ in 0..n {
            match w.cast(&origin, &dir, 30.0, &mut rng) {
                Some(d) if (d - 1.0).abs() < EPS => glass += 1,
                Some(d) if (d - 3.0).abs() < EPS => corridor += 1,
                None => lost += 1,
                Some(d) => panic!("unexpected distance {d}"),
            }
        }
        let frac = |k: i32| f64::from(k) / f64::from(n);
        // Standard error ≈ 0.0035; allow about 4 σ.
        assert!(
            (frac(glass) - GLASS_P_RETURN).abs() < 0.015,
            "glass {}",
            frac(glass)
        );
        assert!(
            (frac(corridor) - GLASS_P_PASS).abs() < 0.015,
            "corridor {}",
            frac(corridor)
        );
        assert!((frac(lost) - 0.2).abs() < 0.015, "lost {}", frac(lost));
    }

    fn scanner(pose: Isometry3<f64>, min: f64, max: f64) -> Scanner {
        Scanner {
            world: Arc::new(World::conference_room()),
            pose,
            noise: RangeNoise::NONE,
            min_range_m: min,
            max_range_m: max,
        }
    }

    #[test]
    fn scanner_without_noise_measures_exact_ranges() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let flat = scanner(Isometry3::translation(4.0, 3.0, 1.5), 0.1, 40.0);
        use std::f64::consts::{FRAC_PI_2, PI};
        assert_near(flat.measure(0.0, &mut rng), 4.0); // east wall
        assert_near(flat.measure(PI, &mut rng), 4.0); // west wall
        assert_near(flat.measure(-FRAC_PI_2, &mut rng), 3.0); // south wall
        // A vertical scanner: sensor +y turned onto world +z (rotation of +90° about x).
        let rot = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), FRAC_PI_2);
        let vertical = Isometry3::from_parts(Translation3::new(4.0, 3.0, 1.5), rot);
        let v = scanner(vertical, 0.1, 40.0);
        assert_near(v.measure(FRAC_PI_2, &mut rng), 1.5); // ceiling
        assert_near(v.measure(-FRAC_PI_2, &mut rng), 0.75); // table top
        assert_near(v.measure(0.0, &mut rng), 4.0); // east wall
    }

    #[test]
    fn scanner_respects_min_and_max_range() {
        use std::f64::consts::FRAC_PI_2;
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let rot = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), FRAC_PI_2);
        let pose = Isometry3::from_parts(Translation3::new(4.0, 3.0, 1.5), rot);
        let s = scanner(pose, 1.0, 3.5);
        assert_eq!(s.measure(-FRAC_PI_2, &mut rng), None); // table at 0.75 < 1.0
        assert_eq!(s.measure(0.0, &mut rng), None); // wall at 4.0 > 3.5
        assert_near(s.measure(FRAC_PI_2, &mut rng), 1.5); // ceiling within range
    }

    #[test]
    fn shipped_toml_equals_the_built_in_room() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/worlds/conference_room.toml");
        let loaded = World::load(path).map_err(|e| e.to_string());
        assert_eq!(loaded, Ok(World::conference_room()));
    }

    #[test]
    fn ground_truth_helpers() {
        let w = World::conference_room();
        assert_eq!(w.primitives().count(), 28);
        assert_eq!(w.room(), Aabb::new([0.0, 0.0, 0.0], [8.0, 6.0, 3.0]));
        assert_eq!(w.bounds(), Aabb::new([-0.1, -1.0, -0.1], [10.1, 8.1, 3.1]));
        assert!(!w.is_inside_solid(&Point3::new(4.0, 3.0, 1.5)));
        assert!(!w.is_inside_solid(&Point3::new(7.0, 5.9, 2.0)));
        assert!(w.is_inside_solid(&Point3::new(4.0, 3.0, 0.73))); // table top
        assert!(w.is_inside_solid(&Point3::new(3.2, 1.52, 0.5))); // chair backrest
        assert!(w.is_inside_solid(&Point3::new(0.5, 0.5, 0.7))); // stacked box
        assert!(w.is_inside_solid(&Point3::new(9.0, 1.5, 1.0))); // hall, outside the room
        assert!(w.is_inside_solid(&Point3::new(4.0, 7.0, 1.0))); // corridor
        assert!(w.is_inside_solid(&Point3::new(4.0, 3.0, -0.05))); // in the floor slab
    }

    fn err(text: &str) -> String {
        match World::from_toml_str(text) {
            Ok(_) => panic!("accepted:\n{text}"),
            Err(e) => e.to_string(),
        }
    }

    const ROOM: &str = "[room]\nmin = [0, 0, 0]\nmax = [8, 6, 3]\n";

    #[test]
    fn toml_errors_name_the_line_and_field() {
        let missing = err(&format!("{ROOM}\n[[box]]\nname = \"t\"\nmin = [0, 0, 0]\n"));
        assert!(
            missing.contains("line 5") && missing.contains("missing field `max`"),
            "{missing}"
        );

        let typo = err(&format!(
            "{ROOM}[[box]]\nname = \"t\"\nmin = [0,0,0]\nmax = [1,1,1]\nmaterail = \"opaque\"\n"
        ));
        assert!(
            typo.contains("line 8") && typo.contains("materail"),
            "{typo}"
        );

        let short = err(&format!(
            "{ROOM}[[box]]\nname = \"t\"\nmin = [0, 0]\nmax = [1,1,1]\n"
        ));
        assert!(short.contains("line 6"), "{short}");

        let syntax = err("[room\nmin = [0, 0, 0]\n");
        assert!(syntax.contains("line 1"), "{syntax}");

        let inverted = err(&format!(
            "{ROOM}\n[[box]]\nname = \"table\"\nmin = [0, 0, 0.75]\nmax = [1, 1, 0.72]\n"
        ));
        assert_eq!(
            inverted,
            "line 5, box \"table\": min.z (0.75) must be less than max.z (0.72)"
        );

        let glass = err(&format!(
            "{ROOM}[[box]]\nname = \"g\"\nmin = [0,0,0]\nmax = [1,1,1]\n\
             material = {{ glass = {{ p_return = 0.7, p_pass = 0.5 }} }}\n"
        ));
        assert_eq!(
            glass,
            "line 4, box \"g\": glass p_return + p_pass (1.2) must not exceed 1"
        );

        let skew = err(&format!(
            "{ROOM}[[rect]]\nname = \"r\"\ncorner = [0,0,0]\nedge_u = [1,0,0]\nedge_v = [1,1,0]\n"
        ));
        assert_eq!(
            skew,
            "line 4, rect \"r\": edge_u and edge_v must be perpendicular"
        );

        let room = err("[room]\nmin = [0, 0, 0]\nmax = [8, 0, 3]\n");
        assert_eq!(room, "room: min.y (0) must be less than max.y (0)");

        let file = World::load("/nonexistent/room.toml")
            .map(|_| ())
            .map_err(|e| e.to_string());
        assert!(
            matches!(&file, Err(m) if m.starts_with("cannot read world file /nonexistent/room.toml"))
        );
    }

    #[test]
    fn new_validates_primitives() {
        let bad = Primitive {
            name: "pane".to_owned(),
            shape: Shape::Box(Aabb::new([0.0; 3], [1.0; 3])),
            material: Material::Glass {
                p_return: -0.1,
                p_pass: 0.5,
            },
        };
        let e = World::new(Aabb::new([0.0; 3], [1.0; 3]), vec![bad])
            .map(|_| ())
            .map_err(|e| e.to_string());
        assert_eq!(
            e,
            Err(
                "box #1 \"pane\": glass p_return (-0.1) and p_pass (0.5) must be in [0, 1]"
                    .to_owned()
            )
        );
    }
}
