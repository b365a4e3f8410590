//! Depth registration: point-to-plane ICP between the depth of two views.
//!
//! Appearance (ORB) cannot relate two views of the same surfaces taken from opposite
//! directions — a corridor walked out and back, whose legs a frame drop left unjoined (see
//! `docs/robustness-notes.md`, `loop` one drop) — but their depth can: the walls and the floor
//! are the same planes. This module registers a source point set onto a target's local planes
//! and reports, with the relative pose, the registration's information matrix (the
//! Gauss–Newton Hessian over the residual variance). A pose-graph edge built from it constrains
//! only what the surfaces pin down: along a corridor without doors the length direction keeps
//! (almost) no information, and its smallest eigenvalue says so.
//!
//! Not yet called by the pipeline: the building block of a geometric pose-graph edge between
//! keyframes that share surfaces but no ORB view (what `loop`'s one-drop rows lack; next:
//! keep a subsampled depth cloud per keyframe, pick overlapping keyframe groups across a
//! merge's seam, and add the edges in `global_optimizer`).

use crate::optim::se3;
use nalgebra::{Isometry3, Matrix6, SymmetricEigen, Vector3, Vector6};
use std::collections::HashMap;

/// Settings of a registration.
#[derive(Clone, Debug)]
pub struct RegistrationConfig {
    /// Edge of the cubic cells the target's planes are fitted in (m).
    pub voxel_m: f64,
    /// Fewest target points a cell needs to hold a plane.
    pub min_points_per_plane: usize,
    /// A cell is planar when its smallest covariance eigenvalue is below this share of the
    /// middle one.
    pub max_planarity: f64,
    /// Residuals larger than this (m) are not correspondences.
    pub max_residual_m: f64,
    /// Huber threshold of the point-to-plane residual (m).
    pub huber_m: f64,
    /// Gauss–Newton iterations at most.
    pub iterations: usize,
    /// Fewest correspondences for a result.
    pub min_inliers: usize,
}

impl Default for RegistrationConfig {
    fn default() -> Self {
        Self {
            voxel_m: 0.15,
            min_points_per_plane: 8,
            max_planarity: 0.1,
            max_residual_m: 0.1,
            huber_m: 0.02,
            iterations: 30,
            min_inliers: 300,
        }
    }
}

/// A local plane of the target: a point on it and its unit normal.
#[derive(Clone, Copy, Debug)]
struct Plane {
    centroid: Vector3<f64>,
    normal: Vector3<f64>,
}

/// The target's planes, one per planar cell.
pub struct PlaneMap {
    voxel_m: f64,
    cells: HashMap<(i64, i64, i64), Plane>,
}

impl PlaneMap {
    /// Fits a plane in every cell of `points` that holds enough of them and is flat.
    pub fn new(points: &[Vector3<f64>], cfg: &RegistrationConfig) -> Self {
        let mut groups: HashMap<(i64, i64, i64), Vec<usize>> = HashMap::new();
        for (i, p) in points.iter().enumerate() {
            groups.entry(cell(p, cfg.voxel_m)).or_default().push(i);
        }
        let mut cells = HashMap::new();
        for (key, members) in groups {
            if members.len() < cfg.min_points_per_plane {
                continue;
            }
            let n = members.len() as f64;
            let centroid = members.iter().map(|&i| points[i]).sum::<Vector3<f64>>() / n;
            let cov = members
                .iter()
                .map(|&i| {
                    let d = points[i] - centroid;
                    d * d.transpose()
                })
                .sum::<nalgebra::Matrix3<f64>>()
                / n;
            let eig = cov.symmetric_eigen();
            let mut order = [0, 1, 2];
            order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
            let (l0, l1) = (eig.eigenvalues[order[0]], eig.eigenvalues[order[1]]);
            if l1 <= 0.0 || l0 > cfg.max_planarity * l1 {
                continue;
            }
            let normal = eig.eigenvectors.column(order[0]).into_owned().normalize();
            cells.insert(key, Plane { centroid, normal });
        }
        Self {
            voxel_m: cfg.voxel_m,
            cells,
        }
    }

    /// Number of planar cells.
    pub fn len(&self) -> usize {
        self.cells.len()
    }

    /// True when no cell is planar.
    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }

    /// The plane nearest to `p` among its cell's and the 26 neighbouring cells' (a guess up
    /// to a cell off still finds its surface), with the signed point-to-plane distance.
    fn nearest_plane(&self, p: &Vector3<f64>) -> Option<(&Plane, f64)> {
        let (x, y, z) = cell(p, self.voxel_m);
        let mut best: Option<(&Plane, f64)> = None;
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if let Some(pl) = self.cells.get(&(x + dx, y + dy, z + dz)) {
                        let r = pl.normal.dot(&(p - pl.centroid));
                        if best.is_none_or(|(_, b)| r.abs() < b.abs()) {
                            best = Some((pl, r));
                        }
                    }
                }
            }
        }
        best
    }
}

fn cell(p: &Vector3<f64>, voxel: f64) -> (i64, i64, i64) {
    (
        (p.x / voxel).floor() as i64,
        (p.y / voxel).floor() as i64,
        (p.z / voxel).floor() as i64,
    )
}

/// The result of a registration.
#[derive(Clone, Debug)]
pub struct Registration {
    /// Maps source points into the target's frame.
    pub target_from_source: Isometry3<f64>,
    /// Correspondences used in the last iteration.
    pub inliers: usize,
    /// Root mean square of their point-to-plane residuals (m).
    pub rms_m: f64,
    /// Information of a left perturbation δ = (ω, υ) of `target_from_source`: the Hessian
    /// over the residual variance. Directions the planes do not constrain have (almost) none.
    pub information: Matrix6<f64>,
}

impl Registration {
    /// Eigenvalues and unit eigenvectors of the information, smallest first: the first pair
    /// is the direction the surfaces constrain least.
    pub fn constraint_directions(&self) -> Vec<(f64, Vector6<f64>)> {
        let eig = SymmetricEigen::new(self.information);
        let mut out: Vec<(f64, Vector6<f64>)> = (0..6)
            .map(|i| (eig.eigenvalues[i], eig.eigenvectors.column(i).into_owned()))
            .collect();
        out.sort_by(|a, b| a.0.total_cmp(&b.0));
        out
    }
}

/// Registers `source` (points in its own frame) onto the planes of `target`, from the
/// guess `initial` (target ← source). None when fewer than `min_inliers` source points land
/// on a target plane within `max_residual_m`: the views share too little surface.
pub fn register(
    target: &PlaneMap,
    source: &[Vector3<f64>],
    initial: &Isometry3<f64>,
    cfg: &RegistrationConfig,
) -> Option<Registration> {
    let mut t = *initial;
    let mut last: Option<(Matrix6<f64>, usize, f64)> = None;
    for _ in 0..cfg.iterations {
        let mut h = Matrix6::<f64>::zeros();
        let mut g = Vector6::<f64>::zeros();
        let (mut n, mut sq) = (0usize, 0.0);
        for p in source {
            let q = t.transform_vector(p) + t.translation.vector;
            let Some((plane, r)) = target.nearest_plane(&q) else {
                continue;
            };
            if r.abs() > cfg.max_residual_m {
                continue;
            }
            // Left perturbation: exp(δ)·q ≈ q + ω × q + υ, and n·(ω × q) = ω·(q × n).
            let qn = q.cross(&plane.normal);
            let j = Vector6::new(
                qn.x,
                qn.y,
                qn.z,
                plane.normal.x,
                plane.normal.y,
                plane.normal.z,
            );
            let w = if r.abs() <= cfg.huber_m {
                1.0
            } else {
                cfg.huber_m / r.abs()
            };
            h += w * j * j.transpose();
            g += w * r * j;
            n += 1;
            sq += r * r;
        }
        if n < cfg.min_inliers {
            return None;
        }
        last = Some((h, n, sq));
        // Levenberg damping keeps the unconstrained directions where they are.
        let floor = 1e-6 * h.trace() + 1e-12;
        let damped = h + Matrix6::from_diagonal(&h.diagonal().map(|d| 1e-3 * d + floor));
        let delta = -damped.cholesky()?.solve(&g);
        t = se3::exp(&delta) * t;
        if delta.norm() < 1e-7 {
            break;
        }
    }
    let (h, n, sq) = last?;
    let mean_sq = sq / n as f64;
    // The residuals' own spread (floored at a millimetre) sets the scale of the information.
    Some(Registration {
        target_from_source: t,
        inliers: n,
        rms_m: mean_sq.sqrt(),
        information: h / mean_sq.max(1e-6),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Points sampled on axis-aligned rectangles: (fixed axis, value, ranges of the other two).
    fn sample(
        rng: &mut ChaCha8Rng,
        faces: &[(usize, f64, (f64, f64), (f64, f64))],
        per_face: usize,
        noise: f64,
    ) -> Vec<Vector3<f64>> {
        let mut out = Vec::new();
        for &(axis, value, (a0, a1), (b0, b1)) in faces {
            for _ in 0..per_face {
                let (a, b) = (rng.random_range(a0..a1), rng.random_range(b0..b1));
                let mut p = Vector3::zeros();
                let others: Vec<usize> = (0..3).filter(|&k| k != axis).collect();
                p[axis] = value + rng.random_range(-noise..=noise);
                p[others[0]] = a;
                p[others[1]] = b;
                out.push(p);
            }
        }
        out
    }

    fn pose(t: [f64; 3], rpy_deg: [f64; 3]) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(t[0], t[1], t[2]),
            UnitQuaternion::from_euler_angles(
                rpy_deg[0].to_radians(),
                rpy_deg[1].to_radians(),
                rpy_deg[2].to_radians(),
            ),
        )
    }

    fn errors(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
        let d = a.inverse() * b;
        (d.translation.vector.norm(), d.rotation.angle().to_degrees())
    }

    /// A closed room seen twice: the registration recovers the relative pose from a guess
    /// 10 cm and 3° off, and every direction is constrained.
    #[test]
    fn a_room_is_registered_in_every_direction() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let room = [
            (0, 0.0, (0.0, 3.0), (0.0, 2.5)),
            (0, 4.0, (0.0, 3.0), (0.0, 2.5)),
            (1, 0.0, (0.0, 4.0), (0.0, 2.5)),
            (1, 3.0, (0.0, 4.0), (0.0, 2.5)),
            (2, 0.0, (0.0, 4.0), (0.0, 3.0)),
        ];
        let target = sample(&mut rng, &room, 4000, 0.003);
        let truth = pose([0.3, -0.2, 0.1], [2.0, -1.0, 8.0]);
        // The source sees the same room from elsewhere: its points in its own frame.
        let source: Vec<Vector3<f64>> = sample(&mut rng, &room, 3000, 0.003)
            .into_iter()
            .map(|p| (truth.inverse() * nalgebra::Point3::from(p)).coords)
            .collect();
        let cfg = RegistrationConfig::default();
        let planes = PlaneMap::new(&target, &cfg);
        assert!(planes.len() > 100, "{} planes", planes.len());
        let guess = truth * pose([0.06, -0.05, 0.06], [1.0, 2.0, -2.0]);
        let r = register(&planes, &source, &guess, &cfg).expect("registered");
        let (dt, da) = errors(&r.target_from_source, &truth);
        assert!(dt < 0.003 && da < 0.1, "off by {dt} m, {da}°");
        let dirs = r.constraint_directions();
        assert!(
            dirs[0].0 > 1e-3 * dirs[5].0,
            "a room constrains every direction: {:?}",
            dirs.iter().map(|d| d.0).collect::<Vec<_>>()
        );
    }

    /// A corridor without doors: two walls and a floor. The sideways offset and the heading are
    /// recovered; the length direction is the one the surfaces do not constrain, and the
    /// information says so.
    #[test]
    fn a_corridor_leaves_its_length_free() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let corridor = [
            (1, -1.0, (0.0, 10.0), (0.0, 2.5)),
            (1, 1.0, (0.0, 10.0), (0.0, 2.5)),
            (2, 0.0, (0.0, 10.0), (-1.0, 1.0)),
        ];
        let target = sample(&mut rng, &corridor, 6000, 0.003);
        let truth = pose([0.4, 0.12, 0.0], [0.0, 0.0, 1.0]);
        let source: Vec<Vector3<f64>> = sample(&mut rng, &corridor, 5000, 0.003)
            .into_iter()
            .map(|p| (truth.inverse() * nalgebra::Point3::from(p)).coords)
            .filter(|p| p.x > 2.0 && p.x < 8.0)
            .collect();
        // The guess (identity) is 12 cm off sideways: correspondences up to 25 cm.
        let cfg = RegistrationConfig {
            max_residual_m: 0.25,
            ..Default::default()
        };
        let planes = PlaneMap::new(&target, &cfg);
        let r = register(&planes, &source, &Isometry3::identity(), &cfg).expect("registered");
        let est = r.target_from_source;
        // Sideways and up: recovered. Along the corridor: whatever the guess left.
        assert!(
            (est.translation.y - truth.translation.y).abs() < 0.005,
            "sideways {} against {}",
            est.translation.y,
            truth.translation.y
        );
        assert!(est.translation.z.abs() < 0.005, "up {}", est.translation.z);
        let yaw = est.rotation.euler_angles().2.to_degrees();
        assert!((yaw - 1.0).abs() < 0.05, "heading {yaw}°");
        let dirs = r.constraint_directions();
        let (weakest, v) = &dirs[0];
        assert!(
            *weakest < 1e-3 * dirs[5].0,
            "the corridor's length should be unconstrained: {:?}",
            dirs.iter().map(|d| d.0).collect::<Vec<_>>()
        );
        assert!(
            v[3].abs() > 0.9,
            "weakest direction {v:?} is not the corridor's length"
        );
    }

    /// Views that share no surface give no registration.
    #[test]
    fn no_shared_surface_no_registration() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let target = sample(&mut rng, &[(2, 0.0, (0.0, 2.0), (0.0, 2.0))], 3000, 0.002);
        let source = sample(
            &mut rng,
            &[(2, 0.0, (10.0, 12.0), (10.0, 12.0))],
            3000,
            0.002,
        );
        let cfg = RegistrationConfig::default();
        let planes = PlaneMap::new(&target, &cfg);
        assert!(register(&planes, &source, &Isometry3::identity(), &cfg).is_none());
    }
}
