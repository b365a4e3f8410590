//! Scene geometry: axis-aligned textured rectangles, and builders for rooms, door openings,
//! furniture boxes and posters.
//!
//! World frame: x east, y north, z up, metres; the floor is z = 0. Everything is made of
//! one-sided axis-aligned quads, which keeps ray casting exact and cheap, and makes analytic
//! depth checks trivial.

use crate::texture::Texture;

/// One-sided axis-aligned rectangle. Its normal is `facing` times the unit vector of `axis`;
/// rays hitting its back are ignored, so walls of neighbouring rooms never occlude each other
/// from the wrong side.
#[derive(Debug, Clone)]
pub struct Quad {
    /// Normal axis: 0 = x, 1 = y, 2 = z.
    pub axis: usize,
    /// Plane coordinate along `axis`.
    pub c: f64,
    /// +1 or -1.
    pub facing: f64,
    /// Extent on the two in-plane axes (see [`in_plane`]).
    pub lo: [f64; 2],
    pub hi: [f64; 2],
    /// Index into [`Scene::textures`].
    pub tex: usize,
    /// Texture coordinates are in-plane coordinates minus this origin; equal origins relative to
    /// equal geometry give identical appearance (perceptual aliasing).
    pub uv_origin: [f64; 2],
    /// Lambertian shading factor of a fixed directional light (depends on the normal only, so
    /// appearance does not change with the viewpoint).
    pub shade: f32,
    /// Texture coordinate runs against the in-plane axis (set by [`Scene::append_rotated180`],
    /// so that a rotated copy of a room looks exactly like the original).
    pub flip: [bool; 2],
}

/// The two in-plane axes of a quad whose normal is `axis`: (horizontal, vertical) for walls.
pub fn in_plane(axis: usize) -> (usize, usize) {
    match axis {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    }
}

/// Side of a room, named by the compass direction of the wall.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    South,
    North,
    West,
    East,
}

/// A door opening in a room wall: its centre along the wall, width and height.
#[derive(Debug, Clone, Copy)]
pub struct Door {
    pub side: Side,
    pub center: f64,
    pub width: f64,
    pub height: f64,
}

/// Texture seeds of a room's surfaces, with texture origins (for aliasing).
#[derive(Debug, Clone, Copy)]
pub struct RoomLook {
    pub floor: u64,
    pub ceiling: u64,
    /// South, North, West, East.
    pub walls: [u64; 4],
}

impl RoomLook {
    /// All seeds derived from one seed.
    pub fn from_seed(seed: u64) -> Self {
        let m = crate::texture::mix;
        Self {
            floor: m(seed ^ 1),
            ceiling: m(seed ^ 2),
            walls: [m(seed ^ 3), m(seed ^ 4), m(seed ^ 5), m(seed ^ 6)],
        }
    }
}

/// A named point of interest, e.g. a poster corner, for tests and documentation.
#[derive(Debug, Clone)]
pub struct Landmark {
    pub name: String,
    pub p: [f64; 3],
}

#[derive(Debug, Clone, Default)]
pub struct Scene {
    pub quads: Vec<Quad>,
    pub textures: Vec<Texture>,
    pub landmarks: Vec<Landmark>,
}

fn shade_for(axis: usize, facing: f64) -> f32 {
    match (axis, facing > 0.0) {
        (2, true) => 1.0,   // floor, lit from above
        (2, false) => 0.75, // ceiling
        (0, true) => 0.92,
        (0, false) => 0.8,
        (1, true) => 0.86,
        _ => 0.97,
    }
}

impl Scene {
    pub fn add_texture(&mut self, t: Texture) -> usize {
        self.textures.push(t);
        self.textures.len() - 1
    }

    /// Adds a quad; texture origin given in in-plane coordinates.
    #[allow(clippy::too_many_arguments)]
    pub fn add_quad(
        &mut self,
        axis: usize,
        c: f64,
        facing: f64,
        lo: [f64; 2],
        hi: [f64; 2],
        tex: usize,
        uv_origin: [f64; 2],
    ) {
        if hi[0] - lo[0] <= 1e-9 || hi[1] - lo[1] <= 1e-9 {
            return;
        }
        let shade = shade_for(axis, facing);
        self.quads.push(Quad {
            axis,
            c,
            facing,
            lo,
            hi,
            tex,
            uv_origin,
            shade,
            flip: [false; 2],
        });
    }

    /// A wall (vertical quad facing into a room) with door openings: full-height segments
    /// between doors and lintels above them. `along` is the wall's horizontal range.
    #[allow(clippy::too_many_arguments)]
    pub fn add_wall(
        &mut self,
        axis: usize,
        c: f64,
        facing: f64,
        along: [f64; 2],
        height: f64,
        doors: &[(f64, f64, f64)],
        tex: usize,
        uv_origin: [f64; 2],
    ) {
        let mut ds: Vec<(f64, f64, f64)> = doors.to_vec();
        ds.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut x = along[0];
        for (center, width, dh) in ds {
            let (a, b) = (center - width / 2.0, center + width / 2.0);
            self.add_quad(axis, c, facing, [x, 0.0], [a, height], tex, uv_origin);
            self.add_quad(axis, c, facing, [a, dh], [b, height], tex, uv_origin);
            x = b;
        }
        self.add_quad(
            axis,
            c,
            facing,
            [x, 0.0],
            [along[1], height],
            tex,
            uv_origin,
        );
    }

    /// A rectangular room seen from inside: floor, ceiling and four walls with doors.
    /// Texture origins are the room's south-west corner, so two rooms with the same look and
    /// size are indistinguishable.
    pub fn add_room(
        &mut self,
        min: [f64; 2],
        max: [f64; 2],
        height: f64,
        doors: &[Door],
        look: RoomLook,
    ) {
        let fl = self.add_texture(Texture::floor(look.floor));
        let ce = self.add_texture(Texture::ceiling(look.ceiling));
        self.add_quad(2, 0.0, 1.0, min, max, fl, min);
        self.add_quad(2, height, -1.0, min, max, ce, min);
        let sides = [Side::South, Side::North, Side::West, Side::East];
        for (k, side) in sides.iter().enumerate() {
            let tex = self.add_texture(Texture::wall(look.walls[k]));
            let ds: Vec<(f64, f64, f64)> = doors
                .iter()
                .filter(|d| d.side == *side)
                .map(|d| (d.center, d.width, d.height))
                .collect();
            match side {
                Side::South => self.add_wall(
                    1,
                    min[1],
                    1.0,
                    [min[0], max[0]],
                    height,
                    &ds,
                    tex,
                    [min[0], 0.0],
                ),
                Side::North => self.add_wall(
                    1,
                    max[1],
                    -1.0,
                    [min[0], max[0]],
                    height,
                    &ds,
                    tex,
                    [min[0], 0.0],
                ),
                Side::West => self.add_wall(
                    0,
                    min[0],
                    1.0,
                    [min[1], max[1]],
                    height,
                    &ds,
                    tex,
                    [min[1], 0.0],
                ),
                Side::East => self.add_wall(
                    0,
                    max[0],
                    -1.0,
                    [min[1], max[1]],
                    height,
                    &ds,
                    tex,
                    [min[1], 0.0],
                ),
            }
        }
    }

    /// The reveal of a door opening through a wall of thickness between `w0` and `w1` (the
    /// two wall planes, along y for a north/south door or along x for an east/west one).
    #[allow(clippy::too_many_arguments)]
    pub fn add_door_frame(
        &mut self,
        axis: usize,
        w0: f64,
        w1: f64,
        center: f64,
        width: f64,
        height: f64,
        seed: u64,
    ) {
        let tex = self.add_texture(Texture::frame(seed));
        let (a, b) = (center - width / 2.0, center + width / 2.0);
        let (lo, hi) = (w0.min(w1), w0.max(w1));
        // Jambs are perpendicular to the wall: normal along the wall's horizontal axis.
        let jamb_axis = if axis == 1 { 0 } else { 1 };
        // In-plane coordinates of a jamb: for normal x they are (y, z), for normal y (x, z).
        self.add_quad(jamb_axis, a, 1.0, [lo, 0.0], [hi, height], tex, [lo, 0.0]);
        self.add_quad(jamb_axis, b, -1.0, [lo, 0.0], [hi, height], tex, [lo, 0.0]);
        let top = if axis == 1 {
            ([a, lo], [b, hi])
        } else {
            ([lo, a], [hi, b])
        };
        self.add_quad(2, height, -1.0, top.0, top.1, tex, top.0);
    }

    /// A box standing on the floor (5 outward faces), e.g. a cupboard, table block or sofa.
    pub fn add_box(&mut self, min: [f64; 3], max: [f64; 3], seed: u64) {
        let tex = self.add_texture(Texture::furniture(seed));
        self.add_quad(
            0,
            min[0],
            -1.0,
            [min[1], min[2]],
            [max[1], max[2]],
            tex,
            [min[1], min[2]],
        );
        self.add_quad(
            0,
            max[0],
            1.0,
            [min[1], min[2]],
            [max[1], max[2]],
            tex,
            [min[1], min[2]],
        );
        self.add_quad(
            1,
            min[1],
            -1.0,
            [min[0], min[2]],
            [max[0], max[2]],
            tex,
            [min[0], min[2]],
        );
        self.add_quad(
            1,
            max[1],
            1.0,
            [min[0], min[2]],
            [max[0], max[2]],
            tex,
            [min[0], min[2]],
        );
        self.add_quad(
            2,
            max[2],
            1.0,
            [min[0], min[1]],
            [max[0], max[1]],
            tex,
            [min[0], min[1]],
        );
    }

    /// A poster 1 cm in front of a wall. `wall` is the wall's side (as seen from inside its
    /// room), `c` the wall plane coordinate, `at` the (horizontal, vertical) lower-left corner
    /// in in-plane coordinates, `size` in metres. Records its four corners as landmarks.
    pub fn add_poster(
        &mut self,
        name: &str,
        wall: Side,
        c: f64,
        at: [f64; 2],
        size: [f64; 2],
        seed: u64,
    ) {
        let tex = self.add_texture(Texture::poster(seed, size));
        let (axis, facing) = match wall {
            Side::South => (1, 1.0),
            Side::North => (1, -1.0),
            Side::West => (0, 1.0),
            Side::East => (0, -1.0),
        };
        let pc = c + 0.01 * facing;
        let hi = [at[0] + size[0], at[1] + size[1]];
        self.add_quad(axis, pc, facing, at, hi, tex, at);
        let (ua, va) = in_plane(axis);
        for (k, (h, v)) in [
            (at[0], at[1]),
            (hi[0], at[1]),
            (hi[0], hi[1]),
            (at[0], hi[1]),
        ]
        .iter()
        .enumerate()
        {
            let mut p = [0.0; 3];
            p[axis] = pc;
            p[ua] = *h;
            p[va] = *v;
            self.landmarks.push(Landmark {
                name: format!("{name}/corner{k}"),
                p,
            });
        }
    }

    /// Appends `other` rotated by 180 degrees about the vertical axis through (cx, cy). The
    /// copy is indistinguishable from the original when seen from the corresponding rotated
    /// viewpoint: the basis of the `aliasing` scenario.
    pub fn append_rotated180(&mut self, other: &Scene, cx: f64, cy: f64) {
        let toff = self.textures.len();
        self.textures.extend(other.textures.iter().cloned());
        let ctr = [cx, cy];
        for q in &other.quads {
            let mut r = q.clone();
            r.tex += toff;
            let (ua, va) = in_plane(q.axis);
            if q.axis < 2 {
                r.c = 2.0 * ctr[q.axis] - q.c;
                r.facing = -q.facing;
            }
            for (k, ax) in [ua, va].into_iter().enumerate() {
                if ax < 2 {
                    r.lo[k] = 2.0 * ctr[ax] - q.hi[k];
                    r.hi[k] = 2.0 * ctr[ax] - q.lo[k];
                    r.uv_origin[k] = 2.0 * ctr[ax] - q.uv_origin[k];
                    r.flip[k] = !q.flip[k];
                }
            }
            self.quads.push(r);
        }
        for l in &other.landmarks {
            let p = [2.0 * cx - l.p[0], 2.0 * cy - l.p[1], l.p[2]];
            self.landmarks.push(Landmark {
                name: format!("{}@rot180", l.name),
                p,
            });
        }
    }

    /// Index of the last quad added (for tests that look for a specific surface).
    pub fn last_quad(&self) -> usize {
        self.quads.len() - 1
    }
}
