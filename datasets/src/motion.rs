//! Camera motion from waypoint scripts.
//!
//! A path is a list of waypoints (time, position, yaw, pitch). Between waypoints, position and
//! angles follow cubic Hermite curves whose tangents are Catmull-Rom tangents over the
//! waypoint *times* (C1 in time, so velocity is continuous); a waypoint where the motion stops
//! or reverses gets a zero tangent, so robots start, stop and turn in place smoothly.
//! Orientation is built from yaw (about world z), pitch and a small roll, with TUM camera axes
//! (x right, y down, z forward) in a z-up world. Hand-held jitter is a deterministic sum of
//! sinusoids, so it is smooth (bounded acceleration) and identical for the same seed.

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// One key pose of a path.
#[derive(Debug, Clone, Copy)]
pub struct Waypoint {
    pub t: f64,
    pub pos: Vector3<f64>,
    /// Heading about world z, radians, counter-clockwise from +x (unwrapped: continuous).
    pub yaw: f64,
    /// Elevation of the optical axis, radians (positive looks up).
    pub pitch: f64,
}

/// Camera-to-world rotation for a heading and elevation (roll about the optical axis added).
pub fn look_rotation(yaw: f64, pitch: f64, roll: f64) -> UnitQuaternion<f64> {
    let f = Vector3::new(
        pitch.cos() * yaw.cos(),
        pitch.cos() * yaw.sin(),
        pitch.sin(),
    );
    let r = Vector3::new(yaw.sin(), -yaw.cos(), 0.0);
    let d = f.cross(&r);
    let m = Matrix3::from_columns(&[r, d, f]);
    let base = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m));
    base * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll)
}

/// Heading and elevation that look from `from` towards `to`.
pub fn yaw_pitch(from: Vector3<f64>, to: Vector3<f64>) -> (f64, f64) {
    let d = to - from;
    (d.y.atan2(d.x), d.z.atan2((d.x * d.x + d.y * d.y).sqrt()))
}

/// Small smooth 6-DoF perturbation (hand-held shake, or robot vibration).
#[derive(Debug, Clone)]
pub struct Jitter {
    /// (amplitude, frequency Hz, phase) per component: x, y, z, yaw, pitch, roll.
    terms: [Vec<(f64, f64, f64)>; 6],
}

impl Jitter {
    pub fn none() -> Self {
        Self {
            terms: Default::default(),
        }
    }

    /// `pos_amp` metres and `rot_amp` radians (per component, roughly the standard deviation).
    pub fn new(seed: u64, pos_amp: f64, rot_amp: f64, planar: bool) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut terms: [Vec<(f64, f64, f64)>; 6] = Default::default();
        for (c, comp) in terms.iter_mut().enumerate() {
            let amp = if c < 3 { pos_amp } else { rot_amp };
            if planar && (c == 2 || c == 5) {
                continue;
            }
            for _ in 0..3 {
                let a = amp * rng.random_range(0.3..0.8);
                let f = rng.random_range(0.15..1.2);
                let p = rng.random_range(0.0..std::f64::consts::TAU);
                comp.push((a, f, p));
            }
        }
        Self { terms }
    }

    fn eval(&self, t: f64) -> [f64; 6] {
        let mut out = [0.0; 6];
        for (o, comp) in out.iter_mut().zip(&self.terms) {
            *o = comp
                .iter()
                .map(|(a, f, p)| a * (std::f64::consts::TAU * f * t + p).sin())
                .sum();
        }
        out
    }
}

/// A continuous stretch of motion.
#[derive(Debug, Clone)]
pub struct Path {
    pub waypoints: Vec<Waypoint>,
    pub jitter: Jitter,
}

fn hermite(p1: f64, p2: f64, m1: f64, m2: f64, s: f64, dt: f64) -> f64 {
    let (s2, s3) = (s * s, s * s * s);
    (2.0 * s3 - 3.0 * s2 + 1.0) * p1
        + (s3 - 2.0 * s2 + s) * dt * m1
        + (-2.0 * s3 + 3.0 * s2) * p2
        + (s3 - s2) * dt * m2
}

impl Path {
    pub fn start(&self) -> f64 {
        self.waypoints.first().map_or(0.0, |w| w.t)
    }
    pub fn end(&self) -> f64 {
        self.waypoints.last().map_or(0.0, |w| w.t)
    }

    /// Catmull-Rom tangent of scalar channel `f` at waypoint i; zero at the ends and where the
    /// channel stops or reverses.
    fn tangent(&self, i: usize, f: impl Fn(&Waypoint) -> f64) -> f64 {
        let w = &self.waypoints;
        if i == 0 || i + 1 >= w.len() {
            return 0.0;
        }
        let (a, b, c) = (f(&w[i - 1]), f(&w[i]), f(&w[i + 1]));
        if (b - a) * (c - b) <= 1e-12 {
            return 0.0;
        }
        (c - a) / (w[i + 1].t - w[i - 1].t)
    }

    /// Pose (camera-to-world) at time t, clamped to the path's time range.
    pub fn pose(&self, t: f64) -> Isometry3<f64> {
        let w = &self.waypoints;
        let t = t.clamp(self.start(), self.end());
        let i = w
            .partition_point(|p| p.t <= t)
            .saturating_sub(1)
            .min(w.len().saturating_sub(2));
        let chans: [fn(&Waypoint) -> f64; 5] = [
            |p| p.pos.x,
            |p| p.pos.y,
            |p| p.pos.z,
            |p| p.yaw,
            |p| p.pitch,
        ];
        let mut v = [0.0; 5];
        if w.len() == 1 {
            v = [w[0].pos.x, w[0].pos.y, w[0].pos.z, w[0].yaw, w[0].pitch];
        } else {
            let dt = w[i + 1].t - w[i].t;
            let s = if dt > 0.0 { (t - w[i].t) / dt } else { 0.0 };
            for (k, f) in chans.iter().enumerate() {
                v[k] = hermite(
                    f(&w[i]),
                    f(&w[i + 1]),
                    self.tangent(i, f),
                    self.tangent(i + 1, f),
                    s,
                    dt,
                );
            }
        }
        let j = self.jitter.eval(t);
        let rot = look_rotation(v[3] + j[3], v[4] + j[4], j[5]);
        Isometry3::from_parts(
            Translation3::new(v[0] + j[0], v[1] + j[1], v[2] + j[2]),
            rot,
        )
    }
}

/// Authoring helper for robot-like motion: planar, fixed camera height and pitch, stop-turn-go.
#[derive(Debug, Clone)]
pub struct RobotScript {
    pub height: f64,
    pub pitch: f64,
    pub speed: f64,
    /// Turning rate, rad/s.
    pub turn_rate: f64,
    pub waypoints: Vec<Waypoint>,
    /// Named marks (time) used as step boundaries.
    pub marks: Vec<(String, f64)>,
}

impl RobotScript {
    pub fn new(x: f64, y: f64, yaw_deg: f64, t0: f64, height: f64, pitch_deg: f64) -> Self {
        let wp = Waypoint {
            t: t0,
            pos: Vector3::new(x, y, height),
            yaw: yaw_deg.to_radians(),
            pitch: pitch_deg.to_radians(),
        };
        Self {
            height,
            pitch: pitch_deg.to_radians(),
            speed: 0.5,
            turn_rate: 50f64.to_radians(),
            waypoints: vec![wp],
            marks: vec![],
        }
    }

    fn last(&self) -> Waypoint {
        *self.waypoints.last().expect("script has a start")
    }

    pub fn now(&self) -> f64 {
        self.last().t
    }

    /// Records a named mark at the current time.
    pub fn mark(&mut self, name: &str) -> &mut Self {
        let t = self.now();
        self.marks.push((name.to_string(), t));
        self
    }

    /// Turns in place to heading `yaw_deg` (the shorter way).
    pub fn turn_to(&mut self, yaw_deg: f64) -> &mut Self {
        let l = self.last();
        let d = yaw_deg.to_radians() - l.yaw;
        let d = (d + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
        self.turn_rad(d)
    }

    /// Turns in place by `deg` (positive: counter-clockwise seen from above), the whole way:
    /// 360 is a full turn. The rate eases in and out and peaks at `turn_rate`.
    pub fn turn_by(&mut self, deg: f64) -> &mut Self {
        self.turn_rad(deg.to_radians())
    }

    fn turn_rad(&mut self, d: f64) -> &mut Self {
        let l = self.last();
        if d.abs() < 1e-6 {
            return self;
        }
        // Cubic ease: peak rate is 1.5x the mean, so use the mean = 2/3 of the limit.
        let dt = d.abs() / (self.turn_rate * 2.0 / 3.0);
        self.waypoints.push(Waypoint {
            t: l.t + dt.max(0.3),
            yaw: l.yaw + d,
            ..l
        });
        self
    }

    /// Turns towards (x, y), then drives there in a straight line.
    pub fn go(&mut self, x: f64, y: f64) -> &mut Self {
        let l = self.last();
        let (dx, dy) = (x - l.pos.x, y - l.pos.y);
        let dist = (dx * dx + dy * dy).sqrt();
        if dist < 1e-6 {
            return self;
        }
        self.turn_to(dy.atan2(dx).to_degrees());
        let l = self.last();
        let dt = dist / (self.speed * 2.0 / 3.0);
        self.waypoints.push(Waypoint {
            t: l.t + dt,
            pos: Vector3::new(x, y, self.height),
            ..l
        });
        self
    }

    /// Drives through several points without stopping in between (heading follows the path).
    pub fn via(&mut self, pts: &[(f64, f64)]) -> &mut Self {
        for &(x, y) in pts {
            self.go(x, y);
        }
        self
    }

    /// Stands still for `secs`.
    pub fn wait(&mut self, secs: f64) -> &mut Self {
        let l = self.last();
        self.waypoints.push(Waypoint { t: l.t + secs, ..l });
        self
    }

    /// Looks around in place: turns by `deg` and back.
    pub fn look_around(&mut self, deg: f64) -> &mut Self {
        let y0 = self.last().yaw.to_degrees();
        self.turn_to(y0 + deg)
            .turn_to(y0)
            .turn_to(y0 - deg)
            .turn_to(y0)
    }

    pub fn path(&self, jitter: Jitter) -> Path {
        Path {
            waypoints: self.waypoints.clone(),
            jitter,
        }
    }
}

/// Authoring helper for hand-held motion: positions and look-at targets at given times.
#[derive(Debug, Clone, Default)]
pub struct HandScript {
    pub waypoints: Vec<Waypoint>,
    pub marks: Vec<(String, f64)>,
}

impl HandScript {
    /// Adds a key pose at time t looking from `pos` at `target`. Yaw is unwrapped against the
    /// previous key so the camera never spins the long way round.
    pub fn key(&mut self, t: f64, pos: [f64; 3], target: [f64; 3]) -> &mut Self {
        let (p, q) = (Vector3::from(pos), Vector3::from(target));
        let (mut yaw, pitch) = yaw_pitch(p, q);
        if let Some(l) = self.waypoints.last() {
            while yaw - l.yaw > std::f64::consts::PI {
                yaw -= std::f64::consts::TAU;
            }
            while yaw - l.yaw < -std::f64::consts::PI {
                yaw += std::f64::consts::TAU;
            }
        }
        self.waypoints.push(Waypoint {
            t,
            pos: p,
            yaw,
            pitch,
        });
        self
    }

    pub fn mark(&mut self, name: &str, t: f64) -> &mut Self {
        self.marks.push((name.to_string(), t));
        self
    }

    pub fn path(&self, jitter: Jitter) -> Path {
        Path {
            waypoints: self.waypoints.clone(),
            jitter,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_rotation_has_tum_axes() {
        // Looking along +x with no pitch: camera z = world x, camera y (down) = world -z.
        let r = look_rotation(0.0, 0.0, 0.0);
        let z = r * Vector3::z();
        let y = r * Vector3::y();
        let x = r * Vector3::x();
        assert!((z - Vector3::x()).norm() < 1e-12);
        assert!((y + Vector3::z()).norm() < 1e-12);
        assert!((x + Vector3::y()).norm() < 1e-12);
    }

    /// A full turn in place keeps the position, turns 360° and peaks at the turn rate.
    #[test]
    fn a_full_turn_in_place_peaks_at_the_turn_rate() {
        let mut s = RobotScript::new(1.0, 2.0, 0.0, 0.0, 1.35, -8.0);
        s.turn_rate = 100f64.to_radians();
        s.turn_by(360.0);
        let p = s.path(Jitter::none());
        let dt = 1.0 / 300.0;
        let (mut t, mut peak, mut total) = (0.0, 0.0f64, 0.0);
        let yaw = |t: f64| {
            let z = p.pose(t).rotation * Vector3::z();
            z.y.atan2(z.x)
        };
        while t + dt <= p.end() {
            let d = (yaw(t + dt) - yaw(t) + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
                - std::f64::consts::PI;
            peak = peak.max(d.abs() / dt);
            total += d;
            assert!(
                (p.pose(t).translation.vector - Vector3::new(1.0, 2.0, 1.35)).norm() < 1e-9,
                "moved at {t}"
            );
            t += dt;
        }
        assert!(
            (total.to_degrees() - 360.0).abs() < 1.0,
            "turned {}",
            total.to_degrees()
        );
        assert!(
            (peak.to_degrees() - 100.0).abs() < 1.0,
            "peak {} deg/s",
            peak.to_degrees()
        );
    }

    #[test]
    fn path_is_smooth_and_hits_waypoints() {
        let mut s = RobotScript::new(0.0, 0.0, 0.0, 0.0, 0.4, 10.0);
        s.go(2.0, 0.0).go(2.0, 2.0).wait(1.0);
        let p = s.path(Jitter::none());
        for w in &p.waypoints {
            assert!((p.pose(w.t).translation.vector - w.pos).norm() < 1e-9);
        }
        // Bounded acceleration: second differences at 30 Hz stay small.
        let dt = 1.0 / 30.0;
        let mut t = 0.0;
        let mut prev: Vec<Vector3<f64>> = vec![];
        let mut max_acc: f64 = 0.0;
        while t < p.end() {
            prev.push(p.pose(t).translation.vector);
            if prev.len() >= 3 {
                let n = prev.len();
                let a = (prev[n - 1] - 2.0 * prev[n - 2] + prev[n - 3]) / (dt * dt);
                max_acc = max_acc.max(a.norm());
            }
            t += dt;
        }
        assert!(max_acc < 1.0, "max acceleration {max_acc} m/s^2");
    }
}
