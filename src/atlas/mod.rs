//! The atlas: every map of a run (and of a loaded session), and the closure pools that joined
//! or corrected them.
//!
//! A new map starts whenever tracking is re-acquired after a loss; a validated relocalization
//! merges two maps; a validated loop closure corrects one. Each accepted pool is a
//! *transaction*: the atlas keeps a skeleton of the maps it touched (poses, points and which
//! key point saw which point), so that the Corrupted Map state can revoke it (paper section V:
//! "the wrong loop closures are removed and the graph is optimized again"). Revoking removes
//! the pool's links and keeps everything else: see [`revoke`].
//!
//! Keyframe and point ids are unique across the whole atlas (one high-water mark), so maps can
//! be merged by moving entries and a rolled-back id is never handed out again.

use crate::error::{Error, Result};
use crate::geometry::Sim3;
use crate::map::{KfId, Map, PointId};
use nalgebra::{Isometry3, Matrix6, UnitQuaternion};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

pub mod revoke;
pub use revoke::Revocation;

pub type MapId = u32;
pub type PoolId = u32;

/// A closure constraint between two keyframes, as the pose graph uses it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClosureEdge {
    pub pool: PoolId,
    /// The keyframe (or frame made keyframe) that recognised the place.
    pub query: KfId,
    /// The keyframe it was recognised in.
    pub matched: KfId,
    /// Measured pose of `query` in the frame of `matched`: `T_matched,w · T_query,w⁻¹`, in
    /// the two keyframes' creation units (see `Keyframe::units`).
    pub relative: Isometry3<f64>,
    /// Measured scale of `query`'s camera frame in `matched`'s (monocular: lengths around
    /// the query per length around the match, in creation units; 1 with depth).
    pub scale: f64,
    /// Information (inverse covariance) of `relative`, (ω, υ) order.
    pub information: Matrix6<f64>,
}

impl ClosureEdge {
    /// An edge from the similarity `z` (query camera → matched camera) measured while the
    /// keyframes had units `u_matched` and `u_query`.
    pub fn new(
        pool: PoolId,
        query: KfId,
        matched: KfId,
        z: &Sim3,
        (u_matched, u_query): (f64, f64),
        information: Matrix6<f64>,
    ) -> Self {
        let z = in_units(z, 1.0 / u_matched, u_query);
        Self {
            pool,
            query,
            matched,
            relative: z.to_isometry(),
            scale: z.scale,
            information,
        }
    }

    /// The measurement in the keyframes' current units.
    pub fn measurement(&self, u_matched: f64, u_query: f64) -> Sim3 {
        let z = Sim3 {
            scale: self.scale,
            ..Sim3::from_isometry(&self.relative)
        };
        in_units(&z, u_matched, 1.0 / u_query)
    }
}

/// `S(a) ∘ z ∘ S(b)`, `S(x)` the pure scaling by `x` (exactly `z` when both are 1).
fn in_units(z: &Sim3, a: f64, b: f64) -> Sim3 {
    Sim3 {
        rotation: z.rotation,
        translation: a * z.translation,
        scale: a * z.scale * b,
    }
}

/// What a pool did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum PoolKind {
    /// A loop closure inside one map; `correction` is the drift correction it implied.
    Loop {
        map: MapId,
        correction: SimilarityRecord,
    },
    /// A relocalization that merged map `from` into map `into` with `alignment` (from-world →
    /// into-world; scale 1 with depth).
    Merge {
        into: MapId,
        from: MapId,
        alignment: SimilarityRecord,
    },
    /// A lost camera relocalized in the map it was lost in (monocular Idle, before a new map
    /// was started): the map is unchanged, but what is mapped from then on rests on it.
    Relocalization { map: MapId },
}

/// A [`Sim3`] in a serialisable form.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SimilarityRecord {
    pub rotation: UnitQuaternion<f64>,
    pub translation: nalgebra::Vector3<f64>,
    pub scale: f64,
}

impl From<&Sim3> for SimilarityRecord {
    fn from(s: &Sim3) -> Self {
        Self {
            rotation: UnitQuaternion::from_rotation_matrix(&s.rotation),
            translation: s.translation,
            scale: s.scale,
        }
    }
}

impl From<&SimilarityRecord> for Sim3 {
    fn from(s: &SimilarityRecord) -> Self {
        Sim3 {
            rotation: s.rotation.to_rotation_matrix(),
            translation: s.translation,
            scale: s.scale,
        }
    }
}

/// One accepted closure pool: a transaction of the atlas.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PoolRecord {
    pub id: PoolId,
    pub kind: PoolKind,
    /// Frame and stamp at which the pool was accepted.
    pub frame: usize,
    pub t: f64,
    pub edges: Vec<ClosureEdge>,
    pub rolled_back: bool,
    /// The touched maps as they were before the pool, as skeletons ([`Map::skeleton`]; not
    /// saved: a loaded atlas cannot revoke the previous session's pools).
    #[serde(skip)]
    before: Vec<Map>,
    /// How the world of the maps the pool joined has moved since (a later merge into another
    /// map): the skeletons' world → the current one.
    #[serde(skip)]
    reframed: Option<SimilarityRecord>,
    /// A merge's evidence that the place is the one the map merged into holds, not a copy of
    /// it (not saved: a loaded atlas's merges stand as they are).
    #[serde(skip)]
    pub evidence: Option<MergeEvidence>,
}

/// A merge is provisional until the camera re-observes what only the map merged into had
/// seen ([`crate::components::global_optimizer::unheld_points`]): a copy of a place shares
/// the part both maps saw, not the rest.
#[derive(Debug, Clone, Default)]
pub struct MergeEvidence {
    /// Points of the map merged into beyond the merged place (see `unheld_points`); emptied
    /// once the merge is confirmed.
    pub unheld: BTreeSet<PointId>,
    /// Frames tracked on at least [`MergeEvidence::MIN_POINTS`] of them so far.
    pub frames: usize,
    /// The frame at which the merge was confirmed.
    pub confirmed: Option<usize>,
}

impl MergeEvidence {
    /// Tracked inliers among the unheld points for a frame to count as evidence: as many as
    /// the tracker needs to hold a pose (`tracker.min_inliers`' default), so a few chance
    /// matches do not count.
    pub const MIN_POINTS: usize = 20;
    /// Frames of evidence that confirm a merge: a few, so one frame's chance matches do not.
    pub const MIN_FRAMES: usize = 3;

    /// Counts one tracked frame's inliers (`matched`); returns true when this frame confirms
    /// the merge.
    pub fn observe(&mut self, matched: impl Iterator<Item = PointId>, frame: usize) -> bool {
        if self.confirmed.is_some() {
            return false;
        }
        let n = matched.filter(|p| self.unheld.contains(p)).count();
        if n < Self::MIN_POINTS {
            return false;
        }
        self.frames += 1;
        if self.frames >= Self::MIN_FRAMES {
            self.confirmed = Some(frame);
            self.unheld = BTreeSet::new();
            return true;
        }
        false
    }
}

impl PoolRecord {
    /// Maps this pool touched.
    pub fn maps(&self) -> Vec<MapId> {
        match &self.kind {
            PoolKind::Loop { map, .. } | PoolKind::Relocalization { map } => vec![*map],
            PoolKind::Merge { into, from, .. } => vec![*into, *from],
        }
    }

    /// Whether this pool can still be undone in this session.
    pub fn undoable(&self) -> bool {
        !self.rolled_back && !self.before.is_empty()
    }

    /// For a merge that can still be undone: the keyframes of map `into` and of map `from`
    /// as they were before it. A wrong merge misplaces one side against the other, so the
    /// contradictions it causes run across this seam.
    pub fn merge_sides(&self) -> Option<(BTreeSet<KfId>, BTreeSet<KfId>)> {
        let PoolKind::Merge { into, from, .. } = self.kind else {
            return None;
        };
        let kfs = |id: MapId| {
            self.before
                .iter()
                .find(|m| m.id == id)
                .map(|m| m.keyframes.keys().copied().collect())
        };
        Some((kfs(into)?, kfs(from)?))
    }
}

/// Every map of the run.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Atlas {
    pub maps: BTreeMap<MapId, Map>,
    pub pools: Vec<PoolRecord>,
    next_map: MapId,
    /// Next unused keyframe and point ids across every map, past and present.
    high_water: (KfId, PointId),
    /// Maps that came from a loaded atlas file (an earlier session).
    pub loaded: Vec<MapId>,
}

/// File header: magic, then version, payload length and CRC-32 of the payload.
const MAGIC: &[u8; 13] = b"homing-atlas\n";
/// 4: keyframes say whether they are panoramic (decision 0030).
pub const ATLAS_VERSION: u32 = 4;

/// What is saved besides the maps, to refuse an atlas made with another camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AtlasCamera {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
}

impl From<&crate::config::CameraConfig> for AtlasCamera {
    fn from(c: &crate::config::CameraConfig) -> Self {
        Self {
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
            width: c.width,
            height: c.height,
        }
    }
}

#[derive(Serialize, Deserialize)]
struct AtlasFile {
    camera: AtlasCamera,
    /// Monocular maps have no metric scale; mixing them with RGB-D sessions is refused.
    mono: bool,
    atlas: Atlas,
}

impl Atlas {
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds an empty map and returns its id.
    pub fn new_map(&mut self) -> MapId {
        let map = self.blank_map();
        self.insert_map(map)
    }

    /// An empty map with the next id and id counters past every id in the atlas, for a
    /// component to build (the initializer); install it with [`Atlas::insert_map`].
    pub fn blank_map(&mut self) -> Map {
        self.refresh_high_water();
        let mut map = Map::new(self.next_map);
        map.reserve_ids(self.high_water);
        map
    }

    /// Installs a map made from [`Atlas::blank_map`].
    pub fn insert_map(&mut self, mut map: Map) -> MapId {
        let id = self.next_map;
        self.next_map += 1;
        // A map not made by blank_map would carry colliding ids; its id at least is fixed.
        debug_assert_eq!(map.id, id, "insert_map wants a map from blank_map");
        map.id = id;
        self.note_ids(&map);
        self.maps.insert(id, map);
        id
    }

    /// The next map id [`Atlas::insert_map`] will hand out.
    pub fn next_map_id(&self) -> MapId {
        self.next_map
    }

    /// Prepares `map` to allocate ids (call before mapping in it): its counters move past every
    /// id the atlas has ever handed out.
    pub fn activate(&mut self, map: MapId) {
        self.refresh_high_water();
        if let Some(m) = self.maps.get_mut(&map) {
            m.reserve_ids(self.high_water);
        }
    }

    fn note_ids(&mut self, map: &Map) {
        let (k, p) = map.next_ids();
        self.high_water = (self.high_water.0.max(k), self.high_water.1.max(p));
    }

    fn refresh_high_water(&mut self) {
        let ids: Vec<(KfId, PointId)> = self.maps.values().map(Map::next_ids).collect();
        for (k, p) in ids {
            self.high_water = (self.high_water.0.max(k), self.high_water.1.max(p));
        }
    }

    /// Removes a map that no pool involves (see the controller's unconfirmed maps); its ids
    /// are never reused.
    pub fn discard_map(&mut self, id: MapId) -> Option<Map> {
        self.refresh_high_water();
        self.loaded.retain(|&m| m != id);
        self.maps.remove(&id)
    }

    /// The map with the most keyframes (ties: the lower id).
    pub fn largest_map(&self) -> Option<MapId> {
        self.maps
            .values()
            .max_by(|a, b| {
                a.keyframes
                    .len()
                    .cmp(&b.keyframes.len())
                    .then(b.id.cmp(&a.id))
            })
            .map(|m| m.id)
    }

    /// The map holding keyframe `kf`.
    pub fn map_of_keyframe(&self, kf: KfId) -> Option<MapId> {
        self.maps
            .values()
            .find(|m| m.keyframes.contains_key(&kf))
            .map(|m| m.id)
    }

    pub fn n_keyframes(&self) -> usize {
        self.maps.values().map(|m| m.keyframes.len()).sum()
    }

    /// Every keyframe of every map.
    pub fn keyframe_ids(&self) -> std::collections::BTreeSet<KfId> {
        self.maps
            .values()
            .flat_map(|m| m.keyframes.keys().copied())
            .collect()
    }

    /// Opens a transaction: snapshots the maps a new pool is about to touch and records it.
    /// Returns the pool id; its edges are added with [`Atlas::add_edges`].
    pub fn begin_pool(&mut self, kind: PoolKind, frame: usize, t: f64) -> PoolId {
        self.refresh_high_water();
        let id = self.pools.len() as PoolId;
        let mut rec = PoolRecord {
            id,
            kind,
            frame,
            t,
            edges: Vec::new(),
            rolled_back: false,
            before: Vec::new(),
            reframed: None,
            evidence: None,
        };
        rec.before = rec
            .maps()
            .iter()
            .filter_map(|m| self.maps.get(m).map(Map::skeleton))
            .collect();
        self.pools.push(rec);
        id
    }

    /// Per standing loop pool, the standing merge pools of its map (older than it) whose seam
    /// one of its closures crosses: one keyframe of the map merged into, the other of the map
    /// merged or made after the merge (which continues the camera's path, and the merge
    /// brought the camera over from the merged map). Such a loop re-measured what the merge
    /// joined: if it was wrong, the merge that let it close is suspect too.
    pub fn loops_across_merges(&self) -> BTreeMap<PoolId, Vec<PoolId>> {
        let mut out: BTreeMap<PoolId, Vec<PoolId>> = BTreeMap::new();
        for l in self.pools.iter().filter(|p| p.undoable()) {
            let PoolKind::Loop { map, .. } = l.kind else {
                continue;
            };
            for merge in self
                .pools
                .iter()
                .filter(|p| p.undoable() && p.id < l.id && p.maps().contains(&map))
            {
                let Some((into, _)) = merge.merge_sides() else {
                    continue;
                };
                let merged_side = |k: KfId| !into.contains(&k);
                if l.edges
                    .iter()
                    .any(|e| merged_side(e.query) != merged_side(e.matched))
                {
                    out.entry(l.id).or_default().push(merge.id);
                }
            }
        }
        out
    }

    /// How far loop pool `pool`'s correction moves the keyframe that recognised the place:
    /// metres there, and degrees. `None` for a merge, or when that keyframe is gone.
    pub fn loop_jump(&self, pool: PoolId) -> Option<(f64, f64)> {
        let p = self.pools.get(pool as usize)?;
        let PoolKind::Loop { map, correction } = &p.kind else {
            return None;
        };
        let m = self.maps.get(map)?;
        let query = p.edges.iter().find_map(|e| m.keyframes.get(&e.query))?;
        let c = query.pose_cw.inverse().translation.vector;
        let s = Sim3::from(correction);
        Some((
            (s.transform_point(&c) - c).norm(),
            s.rotation.angle().to_degrees(),
        ))
    }

    pub fn add_edges(&mut self, pool: PoolId, edges: impl IntoIterator<Item = ClosureEdge>) {
        if let Some(p) = self.pools.get_mut(pool as usize) {
            p.edges.extend(edges);
        }
    }

    /// Closure edges of pools that stand (not rolled back) whose keyframes are both in `map`.
    pub fn closure_edges(&self, map: MapId) -> Vec<ClosureEdge> {
        let Some(m) = self.maps.get(&map) else {
            return Vec::new();
        };
        self.pools
            .iter()
            .filter(|p| !p.rolled_back)
            .flat_map(|p| p.edges.iter())
            .filter(|e| m.keyframes.contains_key(&e.query) && m.keyframes.contains_key(&e.matched))
            .cloned()
            .collect()
    }

    /// Moves every keyframe and point of map `from` into map `into`, expressed in `into`'s frame
    /// through `s` (from-world → into-world). `from` disappears.
    pub fn merge(&mut self, into: MapId, from: MapId, s: &Sim3) -> Result<()> {
        if into == from {
            return Err(Error::invalid(format!(
                "cannot merge map {into} into itself"
            )));
        }
        let src = self
            .maps
            .remove(&from)
            .ok_or_else(|| Error::invalid(format!("merge: no map {from}")))?;
        let Some(dst) = self.maps.get_mut(&into) else {
            self.maps.insert(from, src);
            return Err(Error::invalid(format!("merge: no map {into}")));
        };
        // Pools whose world is in `from` now live in `into`'s. A pool's world is the one its
        // skeletons are restored in: a merge's map merged into (its own `from` is placed by
        // its alignment), a loop's or relocalization's map.
        for p in self.pools.iter_mut().filter(|p| p.undoable()) {
            let world = match p.kind {
                PoolKind::Merge { into, .. } => into,
                PoolKind::Loop { map, .. } | PoolKind::Relocalization { map } => map,
            };
            let inside = p
                .before
                .iter()
                .filter(|m| m.id == world)
                .flat_map(|m| m.keyframes.keys())
                .any(|k| src.keyframes.contains_key(k));
            if inside {
                let old: Sim3 = p.reframed.as_ref().map_or(Sim3::identity(), Sim3::from);
                p.reframed = Some((&s.compose(&old)).into());
            }
        }
        let src = transformed(src, s);
        dst.absorb(src);
        self.refresh_high_water();
        Ok(())
    }

    /// The most recent pool that stands and can be undone.
    pub fn last_undoable_pool(&self) -> Option<PoolId> {
        self.pools.iter().rev().find(|p| p.undoable()).map(|p| p.id)
    }

    /// Writes the atlas (versioned, checksummed, atomically).
    pub fn save(&self, path: &Path, camera: AtlasCamera, mono: bool) -> Result<()> {
        let file = AtlasFile {
            camera,
            mono,
            atlas: self.clone(),
        };
        let payload = postcard::to_stdvec(&file)
            .map_err(|e| Error::file(path, format!("cannot serialise the atlas: {e}")))?;
        let mut bytes = Vec::with_capacity(payload.len() + 32);
        bytes.extend_from_slice(MAGIC);
        bytes.extend_from_slice(&ATLAS_VERSION.to_le_bytes());
        bytes.extend_from_slice(&(payload.len() as u64).to_le_bytes());
        bytes.extend_from_slice(&crc32fast::hash(&payload).to_le_bytes());
        bytes.extend_from_slice(&payload);
        crate::io::atomic_write(path, &bytes)
    }

    /// Reads an atlas written by [`Atlas::save`], refusing files of another version, camera or
    /// modality, and truncated or corrupt files, with a message that says which.
    pub fn load(path: &Path, camera: &AtlasCamera, mono: bool) -> Result<Atlas> {
        let bytes =
            std::fs::read(path).map_err(|e| Error::file(path, format!("cannot read: {e}")))?;
        let header = MAGIC.len() + 4 + 8 + 4;
        if bytes.len() < MAGIC.len() || &bytes[..MAGIC.len()] != MAGIC {
            return Err(Error::file(path, "not a homing atlas file (bad magic)"));
        }
        if bytes.len() < header {
            return Err(Error::file(
                path,
                "truncated atlas file (incomplete header)",
            ));
        }
        let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
        let version = u32_at(MAGIC.len());
        if version != ATLAS_VERSION {
            return Err(Error::file(
                path,
                format!(
                    "atlas format version {version}; this homing reads version {ATLAS_VERSION}"
                ),
            ));
        }
        let len = u64::from_le_bytes(
            bytes[MAGIC.len() + 4..MAGIC.len() + 12]
                .try_into()
                .expect("8 bytes"),
        );
        let crc = u32_at(MAGIC.len() + 12);
        let payload = &bytes[header..];
        if (payload.len() as u64) != len {
            return Err(Error::file(
                path,
                format!(
                    "truncated or padded atlas file: payload is {} bytes, header says {len}",
                    payload.len()
                ),
            ));
        }
        if crc32fast::hash(payload) != crc {
            return Err(Error::file(path, "corrupt atlas file (checksum mismatch)"));
        }
        let file: AtlasFile = postcard::from_bytes(payload)
            .map_err(|e| Error::file(path, format!("corrupt atlas file: {e}")))?;
        if file.mono != mono {
            let kind = |m: bool| if m { "monocular" } else { "RGB-D" };
            return Err(Error::file(
                path,
                format!(
                    "the atlas is {} but this run is {}",
                    kind(file.mono),
                    kind(mono)
                ),
            ));
        }
        let c = &file.camera;
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-6 * a.abs().max(1.0);
        if c.width != camera.width
            || c.height != camera.height
            || !close(c.fx, camera.fx)
            || !close(c.fy, camera.fy)
            || !close(c.cx, camera.cx)
            || !close(c.cy, camera.cy)
        {
            return Err(Error::file(
                path,
                format!(
                    "the atlas was made with another camera ({}x{} fx={} fy={} cx={} cy={}; this run: {}x{} fx={} fy={} cx={} cy={})",
                    c.width,
                    c.height,
                    c.fx,
                    c.fy,
                    c.cx,
                    c.cy,
                    camera.width,
                    camera.height,
                    camera.fx,
                    camera.fy,
                    camera.cx,
                    camera.cy
                ),
            ));
        }
        let mut atlas = file.atlas;
        atlas.loaded = atlas.maps.keys().copied().collect();
        atlas.refresh_high_water();
        for m in atlas.maps.values_mut() {
            m.rebuild_after_load();
            m.check_links()
                .map_err(|e| Error::file(path, format!("corrupt atlas file: map {}: {e}", m.id)))?;
        }
        Ok(atlas)
    }
}

/// `map` expressed in another world frame: `s` maps its world coordinates to the new ones.
pub(crate) fn transformed(mut map: Map, s: &Sim3) -> Map {
    let rot = UnitQuaternion::from_rotation_matrix(&s.rotation);
    for kf in map.keyframes.values_mut() {
        kf.pose_cw = s.transform_pose_cw(&kf.pose_cw);
        // Camera-frame velocity: only its translational part scales.
        for k in 3..6 {
            kf.twist[k] *= s.scale;
        }
        for d in kf.depth.iter_mut() {
            *d *= s.scale as f32;
        }
        kf.units *= s.scale;
    }
    for p in map.points.values_mut() {
        p.position = s.transform_point(&p.position);
        p.normal = rot * p.normal;
        p.min_distance *= s.scale;
        p.max_distance *= s.scale;
    }
    map
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::components::preprocess::Measurement;
    use nalgebra::{Point3, Rotation3, Vector2, Vector3};

    fn measurement(frame: usize) -> Measurement {
        let uvs = (0..10).map(|i| Vector2::new(10.0 * i as f64, 20.0));
        Measurement::synthetic(frame, uvs, 0.0, 1.0, vec![[frame as u8; 32]; 10])
    }

    fn small_map(atlas: &mut Atlas, frame: usize) -> MapId {
        let id = atlas.new_map();
        let map = atlas.maps.get_mut(&id).unwrap();
        let kf = map.add_keyframe(&measurement(frame), Isometry3::translation(0.1, 0.0, 0.0));
        for i in 0..3 {
            map.add_point(kf, i, Vector3::new(i as f64, 0.0, 2.0), 1.2, 8);
        }
        id
    }

    #[test]
    fn ids_are_unique_across_maps_and_merges() {
        let mut atlas = Atlas::new();
        let a = small_map(&mut atlas, 0);
        let b = small_map(&mut atlas, 1);
        let ka: Vec<KfId> = atlas.maps[&a].keyframes.keys().copied().collect();
        let kb: Vec<KfId> = atlas.maps[&b].keyframes.keys().copied().collect();
        assert!(ka.iter().all(|k| !kb.contains(k)), "{ka:?} {kb:?}");
        let pa: Vec<PointId> = atlas.maps[&a].points.keys().copied().collect();
        let pb: Vec<PointId> = atlas.maps[&b].points.keys().copied().collect();
        assert!(pa.iter().all(|p| !pb.contains(p)));
        atlas.merge(a, b, &Sim3::identity()).unwrap();
        assert_eq!(atlas.maps.len(), 1);
        assert_eq!(atlas.maps[&a].keyframes.len(), 2);
        assert_eq!(atlas.maps[&a].points.len(), 6);
        atlas.activate(a);
        let m = atlas.maps.get_mut(&a).unwrap();
        let k = m.add_keyframe(&measurement(2), Isometry3::identity());
        assert!(!ka.contains(&k) && !kb.contains(&k));
    }

    #[test]
    fn merge_moves_geometry_into_the_target_frame() {
        let mut atlas = Atlas::new();
        let a = small_map(&mut atlas, 0);
        let b = small_map(&mut atlas, 1);
        let s = Sim3 {
            rotation: Rotation3::from_euler_angles(0.1, -0.2, 0.3),
            translation: Vector3::new(1.0, 2.0, 3.0),
            scale: 1.0,
        };
        let kf_b = *atlas.maps[&b].keyframes.keys().next().unwrap();
        let pt_b = *atlas.maps[&b].points.keys().next().unwrap();
        let (c_before, x_before) = (
            atlas.maps[&b].keyframes[&kf_b].center(),
            atlas.maps[&b].points[&pt_b].position,
        );
        // The point's camera coordinates must not change (the camera saw it where it saw it).
        let pc_before = atlas.maps[&b].keyframes[&kf_b].pose_cw * Point3::from(x_before);
        atlas.merge(a, b, &s).unwrap();
        let m = &atlas.maps[&a];
        let (c, x) = (m.keyframes[&kf_b].center(), m.points[&pt_b].position);
        assert!((c - s.transform_point(&c_before)).norm() < 1e-12);
        assert!((x - s.transform_point(&x_before)).norm() < 1e-12);
        let pc = m.keyframes[&kf_b].pose_cw * Point3::from(x);
        assert!((pc - pc_before).norm() < 1e-12);
    }

    /// A loop's jump is measured where its query keyframe is: a correction that turns the map
    /// by 180° about a point 5 m from that keyframe moves it by 10 m, whatever the origin.
    #[test]
    fn a_loop_jump_is_measured_at_its_query_keyframe() {
        let mut atlas = Atlas::new();
        let a = small_map(&mut atlas, 0);
        let kf = *atlas.maps[&a].keyframes.keys().next().unwrap();
        let c = atlas.maps[&a].keyframes[&kf].center();
        // 180° about the vertical through the point 5 m along x from the keyframe.
        let pivot = c + Vector3::new(5.0, 0.0, 0.0);
        let rotation = Rotation3::from_euler_angles(0.0, std::f64::consts::PI, 0.0);
        let s = Sim3 {
            rotation,
            translation: pivot - rotation * pivot,
            scale: 1.0,
        };
        let p = atlas.begin_pool(
            PoolKind::Loop {
                map: a,
                correction: (&s).into(),
            },
            5,
            5.0,
        );
        assert_eq!(atlas.loop_jump(p), None, "no edge names the query yet");
        atlas.add_edges(
            p,
            [ClosureEdge::new(
                p,
                kf,
                kf,
                &Sim3::identity(),
                (1.0, 1.0),
                Matrix6::identity(),
            )],
        );
        let (metres, degrees) = atlas.loop_jump(p).unwrap();
        assert!((metres - 10.0).abs() < 1e-9, "{metres}");
        assert!((degrees - 180.0).abs() < 1e-6, "{degrees}");
    }

    /// A relocalization in the lost map revoked before the camera made a keyframe: the camera's
    /// side has nothing to hold the frames tracked since, and they stay posed where they were
    /// tracked (issue #77: a revocation discards no tracked pose).
    #[test]
    fn a_revoked_relocalization_leaves_its_frames_where_they_were_tracked() {
        let mut atlas = Atlas::new();
        let a = small_map(&mut atlas, 0);
        atlas.activate(a);
        let ka = *atlas.maps[&a].keyframes.keys().next().unwrap();
        let p = atlas.begin_pool(PoolKind::Relocalization { map: a }, 5, 5.0);
        let r = atlas.revoke(p, ORB, &[]).unwrap();
        let rel = Isometry3::translation(0.0, 0.1, 0.0);
        assert_eq!(r.reanchor(6, ka, &rel), None);
        assert!(atlas.maps[&a].keyframes.contains_key(&ka));
    }

    /// Merges map `b` into map `a` (identity alignment) as pool of frame 5; returns the pool.
    fn merged_at_frame_5(atlas: &mut Atlas, a: MapId, b: MapId) -> PoolId {
        let p = atlas.begin_pool(
            PoolKind::Merge {
                into: a,
                from: b,
                alignment: (&Sim3::identity()).into(),
            },
            5,
            5.0,
        );
        atlas.merge(a, b, &Sim3::identity()).unwrap();
        atlas.activate(a);
        p
    }

    #[test]
    fn a_loop_between_the_merged_sides_crosses_the_merge() {
        let mut atlas = Atlas::new();
        let a = small_map(&mut atlas, 0);
        let b = small_map(&mut atlas, 1);
        let ka = *atlas.maps[&a].keyframes.keys().next().unwrap();
        let kb = *atlas.maps[&b].keyframes.keys().next().unwrap();
        let merge = merged_at_frame_5(&mut atlas, a, b);
        let map = atlas.maps.get_mut(&a).unwrap();
        let later = map.add_keyframe(&measurement(6), Isometry3::identity());
        let later2 = map.add_keyframe(&measurement(7), Isometry3::identity());
        let loop_pool = |atlas: &mut Atlas, frame: usize, q: KfId, m: KfId| {
            let p = atlas.begin_pool(
                PoolKind::Loop {
                    map: a,
                    correction: (&Sim3::identity()).into(),
                },
                frame,
                frame as f64,
            );
            let e = ClosureEdge::new(p, q, m, &Sim3::identity(), (1.0, 1.0), Matrix6::identity());
            atlas.add_edges(p, [e]);
            p
        };
        // Made after the merge, closing on the map merged into: across the seam.
        let across = loop_pool(&mut atlas, 8, later, ka);
        // From the merged map's side to it: across too.
        let from_merged = loop_pool(&mut atlas, 9, kb, ka);
        // Both ends on the merged side of the seam: not across.
        let same_side = loop_pool(&mut atlas, 10, later2, kb);
        let crossed = atlas.loops_across_merges();
        assert_eq!(crossed.get(&across), Some(&vec![merge]));
        assert_eq!(crossed.get(&from_merged), Some(&vec![merge]));
        assert_eq!(crossed.get(&same_side), None);
        // Once the merge is revoked, nothing is across it.
        atlas.revoke(merge, ORB, &[]).unwrap();
        assert!(atlas.loops_across_merges().is_empty());
    }

    const ORB: (f64, u32) = (1.2, 8);

    /// Every map's keyframes and points reference each other consistently.
    fn links_hold(atlas: &Atlas) {
        for m in atlas.maps.values() {
            m.check_links()
                .unwrap_or_else(|e| panic!("map {}: {e}", m.id));
        }
    }

    #[test]
    fn revoking_a_merge_splits_the_map_and_keeps_what_was_made_since() {
        let mut atlas = Atlas::new();
        let a = small_map(&mut atlas, 0);
        let b = small_map(&mut atlas, 1);
        let ka = *atlas.maps[&a].keyframes.keys().next().unwrap();
        let kb = *atlas.maps[&b].keyframes.keys().next().unwrap();
        let pa: Vec<PointId> = atlas.maps[&a].points.keys().copied().collect();
        let p0 = merged_at_frame_5(&mut atlas, a, b);
        atlas.add_edges(
            p0,
            [ClosureEdge::new(
                p0,
                kb,
                ka,
                &Sim3::identity(),
                (1.0, 1.0),
                Matrix6::identity(),
            )],
        );
        // After the merge the camera (map b's) maps on, seeing map a's points: one key point
        // through a point of its own, one through a's.
        let map = atlas.maps.get_mut(&a).unwrap();
        let later = map.add_keyframe(&measurement(6), Isometry3::translation(0.2, 0.0, 0.0));
        map.observe(later, 0, pa[0]);
        let own = map.add_point(later, 1, Vector3::new(0.5, 0.0, 2.0), 1.2, 8);
        // ... and a's keyframe was fused with a point of b's side (loop fusion).
        let pb0 = *atlas.maps[&a]
            .points
            .iter()
            .find(|(_, p)| p.first_kf == kb)
            .unwrap()
            .0;
        let map = atlas.maps.get_mut(&a).unwrap();
        map.replace_point(pa[1], pb0);
        // A later loop on the camera's side stands after the revocation.
        let p1 = atlas.begin_pool(
            PoolKind::Loop {
                map: a,
                correction: (&Sim3::identity()).into(),
            },
            7,
            7.0,
        );
        let e = ClosureEdge::new(
            p1,
            later,
            kb,
            &Sim3::identity(),
            (1.0, 1.0),
            Matrix6::identity(),
        );
        atlas.add_edges(p1, [e]);
        let keyframes = atlas.n_keyframes();
        links_hold(&atlas);

        let r = atlas.revoke(p0, ORB, &[]).unwrap();
        links_hold(&atlas);
        assert_eq!(atlas.maps.len(), 2);
        assert_eq!(atlas.n_keyframes(), keyframes, "no keyframe is lost");
        assert_eq!((r.far_map, r.near_map), (a, b), "{r:?}");
        assert!(atlas.maps[&a].keyframes.contains_key(&ka));
        assert!(atlas.maps[&b].keyframes.contains_key(&kb));
        assert!(
            atlas.maps[&b].keyframes.contains_key(&later),
            "made by the camera: near"
        );
        assert!(atlas.maps[&b].points.contains_key(&own));
        // The camera's key point that saw a's point sees a copy of it on its side.
        let copy = r
            .copy_in(pa[0], &atlas.maps[&b])
            .expect("a copy on b's side");
        assert_eq!(atlas.maps[&b].keyframes[&later].points[0], Some(copy));
        assert!(atlas.maps[&a].points.contains_key(&pa[0]));
        assert!(
            !atlas.maps[&a].points[&pa[0]]
                .observations
                .contains_key(&later)
        );
        // a's key point fused with b's point gets its own point back.
        assert!(
            atlas.maps[&a].points.contains_key(&pa[1]),
            "the fused point is given back"
        );
        assert_eq!(atlas.maps[&a].keyframes[&ka].points[1], Some(pa[1]));
        assert!(!atlas.maps[&b].points[&pb0].observations.contains_key(&ka));
        assert_eq!(r.points_restored, 1);
        assert!(atlas.pools[p0 as usize].rolled_back);
        assert!(
            !atlas.pools[p1 as usize].rolled_back,
            "a pool of one side stands"
        );
        assert!(
            atlas.revoke(p0, ORB, &[]).is_err(),
            "a pool is revoked once"
        );
        // A frame tracked after the merge against a's keyframe follows the camera's side.
        let rel = Isometry3::translation(0.0, 0.1, 0.0);
        let abs = rel * atlas.maps[&a].keyframes[&ka].pose_cw;
        let (k, rel2, _) = r.reanchor(6, ka, &rel).unwrap();
        assert_eq!(k, later);
        let abs2 = rel2 * atlas.maps[&b].keyframes[&later].pose_cw;
        assert!((abs2.translation.vector - abs.translation.vector).norm() < 1e-12);
        assert!(
            r.reanchor(4, ka, &rel).is_none(),
            "before the merge: a's own frame"
        );
        // New ids never reuse any.
        atlas.activate(b);
        let m = atlas.maps.get_mut(&b).unwrap();
        let k = m.add_keyframe(&measurement(8), Isometry3::identity());
        assert!(k > later);
    }

    #[test]
    fn a_later_pool_across_the_seam_is_revoked_with_the_merge() {
        let mut atlas = Atlas::new();
        let a = small_map(&mut atlas, 0);
        let b = small_map(&mut atlas, 1);
        let ka = *atlas.maps[&a].keyframes.keys().next().unwrap();
        let p0 = merged_at_frame_5(&mut atlas, a, b);
        let later = atlas
            .maps
            .get_mut(&a)
            .unwrap()
            .add_keyframe(&measurement(6), Isometry3::identity());
        let p1 = atlas.begin_pool(
            PoolKind::Loop {
                map: a,
                correction: (&Sim3::identity()).into(),
            },
            7,
            7.0,
        );
        let e = ClosureEdge::new(
            p1,
            later,
            ka,
            &Sim3::identity(),
            (1.0, 1.0),
            Matrix6::identity(),
        );
        atlas.add_edges(p1, [e]);
        let r = atlas.revoke(p0, ORB, &[]).unwrap();
        assert_eq!(r.crossing, vec![p1]);
        assert!(atlas.pools[p1 as usize].rolled_back);
        assert_eq!(atlas.n_keyframes(), 3);
    }

    /// The camera lost track after a wrong merge and was found again in the joined map by
    /// relocalizing against it: what it made from then on is placed by the far side's
    /// structure, and becomes a map of its own when the merge is revoked.
    #[test]
    fn what_the_camera_made_after_it_was_found_again_is_a_map_of_its_own() {
        let mut atlas = Atlas::new();
        let a = small_map(&mut atlas, 0);
        let b = small_map(&mut atlas, 1);
        let ka = *atlas.maps[&a].keyframes.keys().next().unwrap();
        let kb = *atlas.maps[&b].keyframes.keys().next().unwrap();
        let pa = *atlas.maps[&a].points.keys().next().unwrap();
        let p0 = merged_at_frame_5(&mut atlas, a, b);
        atlas.add_edges(
            p0,
            [ClosureEdge::new(
                p0,
                kb,
                ka,
                &Sim3::identity(),
                (1.0, 1.0),
                Matrix6::identity(),
            )],
        );
        let map = atlas.maps.get_mut(&a).unwrap();
        let before = map.add_keyframe(&measurement(6), Isometry3::identity());
        let after = map.add_keyframe(&measurement(9), Isometry3::identity());
        map.observe(after, 2, pa);
        // The near side saw the same far point after the merge, before the camera was lost.
        map.observe(before, 2, pa);
        let r = atlas.revoke(p0, ORB, &[3, 8]).unwrap();
        links_hold(&atlas);
        assert_eq!(atlas.maps.len(), 3);
        assert_eq!(atlas.n_keyframes(), 4);
        let d = r.detached_map.expect("a detached map");
        assert_eq!(r.detached_from, Some(8));
        assert!(atlas.maps[&b].keyframes.contains_key(&before));
        assert!(atlas.maps[&d].keyframes.contains_key(&after));
        assert_eq!(r.camera_map(), d);
        // Each side sees a copy of its own, in its own map.
        let (near_copy, detached_copy) = (
            r.copy_in(pa, &atlas.maps[&b])
                .expect("a copy on the near side"),
            r.copy_in(pa, &atlas.maps[&d])
                .expect("a copy on the detached side"),
        );
        assert_ne!(near_copy, detached_copy);
        assert_eq!(atlas.maps[&b].keyframes[&before].points[2], Some(near_copy));
        assert_eq!(
            atlas.maps[&d].keyframes[&after].points[2],
            Some(detached_copy)
        );
        // Frames tracked against the far side follow the camera's side of their time.
        let rel = Isometry3::identity();
        assert_eq!(r.reanchor(7, ka, &rel).unwrap().0, before);
        assert_eq!(r.reanchor(9, ka, &rel).unwrap().0, after);
    }

    /// A loop's correction bent the map; revoked, every keyframe is back where it was and
    /// the keyframe made since follows the one that recognised the place.
    #[test]
    fn revoking_a_loop_moves_its_correction_back_and_keeps_what_followed() {
        let mut atlas = Atlas::new();
        let a = small_map(&mut atlas, 0);
        let map = atlas.maps.get_mut(&a).unwrap();
        let first = *map.keyframes.keys().next().unwrap();
        let q = map.add_keyframe(&measurement(1), Isometry3::translation(1.0, 0.0, 0.0));
        let qp = map.add_point(q, 4, Vector3::new(1.0, 0.5, 3.0), 1.2, 8);
        let before_q = map.keyframes[&q].pose_cw;
        let correction = Sim3 {
            rotation: Rotation3::from_euler_angles(0.0, 0.3, 0.0),
            translation: Vector3::new(0.5, 0.0, 0.0),
            scale: 1.0,
        };
        let p = atlas.begin_pool(
            PoolKind::Loop {
                map: a,
                correction: (&correction).into(),
            },
            2,
            2.0,
        );
        let e = ClosureEdge::new(
            p,
            q,
            first,
            &Sim3::identity(),
            (1.0, 1.0),
            Matrix6::identity(),
        );
        atlas.add_edges(p, [e]);
        // The loop's optimisation moved the query keyframe and its point.
        let map = atlas.maps.get_mut(&a).unwrap();
        let k = map.keyframes.get_mut(&q).unwrap();
        move_keyframe_for_test(k, &correction);
        let pt = map.points.get_mut(&qp).unwrap();
        pt.position = correction.transform_point(&pt.position);
        let in_q = map.keyframes[&q].pose_cw * Point3::from(map.points[&qp].position);
        // The camera made a keyframe after, 0.2 m on from the corrected query keyframe.
        let after_pose = Isometry3::translation(0.0, 0.0, -0.2) * map.keyframes[&q].pose_cw;
        let after = map.add_keyframe(&measurement(3), after_pose);
        let rel_after = after_pose * map.keyframes[&q].pose_cw.inverse();

        let r = atlas.revoke(p, ORB, &[]).unwrap();
        links_hold(&atlas);
        assert_eq!(atlas.maps.len(), 1);
        assert_eq!(atlas.n_keyframes(), 3);
        let map = &atlas.maps[&a];
        let back = map.keyframes[&q].pose_cw;
        assert!((back.translation.vector - before_q.translation.vector).norm() < 1e-9);
        assert!(back.rotation.angle_to(&before_q.rotation) < 1e-9);
        let rel_now = map.keyframes[&after].pose_cw * back.inverse();
        assert!((rel_now.translation.vector - rel_after.translation.vector).norm() < 1e-9);
        let in_q_now = back * Point3::from(map.points[&qp].position);
        assert!(
            (in_q_now - in_q).norm() < 1e-9,
            "a point moves with its keyframe"
        );
        assert_eq!(r.keyframes_moved, 3);
        assert!(r.far.contains_key(&first));
    }

    fn move_keyframe_for_test(k: &mut crate::map::Keyframe, c: &Sim3) {
        k.pose_cw = c.transform_pose_cw(&k.pose_cw);
    }

    #[test]
    fn save_load_round_trip_and_bad_files() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("atlas.bin");
        let mut atlas = Atlas::new();
        let a = small_map(&mut atlas, 0);
        let cam = AtlasCamera {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
            width: 640,
            height: 480,
        };
        atlas.save(&path, cam.clone(), false).unwrap();
        let back = Atlas::load(&path, &cam, false).unwrap();
        assert_eq!(back.maps[&a].keyframes.len(), 1);
        assert_eq!(back.maps[&a].points.len(), 3);
        assert_eq!(back.loaded, vec![a]);
        let msg = |r: Result<Atlas>| r.unwrap_err().to_string();
        let other = AtlasCamera {
            fx: 520.0,
            ..cam.clone()
        };
        assert!(msg(Atlas::load(&path, &other, false)).contains("another camera"));
        assert!(msg(Atlas::load(&path, &cam, true)).contains("RGB-D"));
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 7]).unwrap();
        assert!(msg(Atlas::load(&path, &cam, false)).contains("truncated"));
        let mut flipped = bytes.clone();
        let n = flipped.len();
        flipped[n - 3] ^= 0x55;
        std::fs::write(&path, &flipped).unwrap();
        assert!(msg(Atlas::load(&path, &cam, false)).contains("checksum"));
        std::fs::write(&path, b"hello").unwrap();
        assert!(msg(Atlas::load(&path, &cam, false)).contains("not a homing atlas"));
        let mut v2 = bytes.clone();
        v2[MAGIC.len()] = 9;
        std::fs::write(&path, &v2).unwrap();
        assert!(msg(Atlas::load(&path, &cam, false)).contains("version 9"));
        let e = msg(Atlas::load(&dir.path().join("missing.bin"), &cam, false));
        assert!(e.contains("missing.bin"));
    }
}
