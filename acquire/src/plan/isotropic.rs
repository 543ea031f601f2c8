//! Isotropic reduction: a sample declared isotropic is measured only at the pairs that are
//! distinct in (θ_l, θ_v, |φ_l − φ_v|); the other pairs are reconstructed on export from
//! their class's representative measurement.
//!
//! **Why |Δφ| and not the signed difference.** Isotropy alone means invariance under a
//! common *rotation* of light and view about the normal, so the BRDF depends on
//! (θ_l, θ_v, φ_l − φ_v). Every isotropic model in the simulator's library (Lambert,
//! Phong variants, Blinn-Phong, isotropic Ward, Cook-Torrance, Oren-Nayar, the microfacet
//! models) is a function of the dot products n·l, n·v and l·v only, and these are also
//! invariant under a *mirror* about any plane containing the normal (φ → −φ). So for them,
//! and for any surface whose microstructure statistics have no handedness, the sign of the
//! azimuth difference does not matter and |Δφ| suffices; the test
//! `isotropic_library_brdfs_are_mirror_symmetric` checks it model by model (and that an
//! anisotropic Ward is not even rotation invariant, so the test can tell them apart).
//! A chiral surface (e.g. a helically twisted weave) would break the mirror step: do not
//! declare such a sample isotropic.
//!
//! **Classes.** Two pairs are equivalent when their θ_l, θ_v and |Δφ| (in [0°, 180°])
//! agree within [`TOLERANCE_DEG`]; with either direction at the pole the azimuth
//! difference is undefined and only the two θ count. Each class is measured once, at its
//! first member in canonical order that the rig can reach (so a rig whose limits miss a
//! pair may still measure a rotated copy of it). A class no member of which is reachable is
//! not reduced: each member gets the ordinary skip / substitute treatment.
//!
//! **Reconstruction.** A member equals `T` applied to its representative, with
//! `T = Rz(ψ)` or `T = Rz(ψ)·M` (M: y → −y, the mirror φ → −φ); [`Equivalent`] stores ψ
//! and whether M is used. For a homogeneous sample the member's image *is* the
//! representative's. For a textured but statistically isotropic sample, the member's image
//! is approximated by the representative's image with the texel grid transformed by `T`
//! (`store::export`, `iso.rs`): the same physical surface rotated by ψ would look like that.
//! The texture is a different patch of the same statistics, not the same texels.

use gonio_dataset::sweep::Pair;
use gonio_devices::Direction;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// Angles (degrees) closer than this count as equal when forming classes: far below any
/// sweep's spacing, far above the rounding of angles computed from vectors.
pub const TOLERANCE_DEG: f64 = 1e-6;

/// One pair that is not measured but reconstructed from its class's representative.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Equivalent {
    /// Canonical index of the omitted pair.
    pub index: usize,
    /// Canonical index of the measured representative.
    pub representative: usize,
    pub light_deg: [f64; 2],
    pub view_deg: [f64; 2],
    /// Rotation ψ about the sample normal (degrees) taking the representative's directions
    /// to this pair's (after the mirror, if any).
    pub rotation_deg: f64,
    /// Whether the mirror φ → −φ is applied before the rotation.
    pub mirrored: bool,
}

/// Azimuth difference of a pair folded into [0°, 180°]; 0 when either direction is at the
/// pole (the difference is undefined there and any value is reached by a rotation).
pub fn abs_delta_phi_deg(light: Direction, view: Direction) -> f64 {
    if is_pole(light) || is_pole(view) {
        return 0.0;
    }
    let d = (light.phi_deg() - view.phi_deg()).rem_euclid(360.0);
    d.min(360.0 - d)
}

fn is_pole(d: Direction) -> bool {
    d.theta_deg() < TOLERANCE_DEG
}

/// The class key: (θ_l, θ_v, |Δφ|) quantized to the tolerance.
fn key(p: &Pair) -> (i64, i64, i64) {
    let q = |x: f64| (x / TOLERANCE_DEG).round() as i64;
    let mut d = abs_delta_phi_deg(p.light, p.view);
    if 180.0 - d < TOLERANCE_DEG {
        d = 180.0;
    }
    (q(p.light.theta_deg()), q(p.view.theta_deg()), q(d))
}

/// Group pairs into isotropy classes; each class lists positions into `pairs` in their
/// order, classes ordered by their first member.
pub fn classes(pairs: &[Pair]) -> Vec<Vec<usize>> {
    let mut by_key: HashMap<(i64, i64, i64), usize> = HashMap::new();
    let mut out: Vec<Vec<usize>> = Vec::new();
    for (i, p) in pairs.iter().enumerate() {
        let c = *by_key.entry(key(p)).or_insert_with(|| {
            out.push(Vec::new());
            out.len() - 1
        });
        out[c].push(i);
    }
    out
}

/// `T(d)` for the transform (ψ, mirrored): mirror φ → −φ first, then rotate by ψ.
pub fn apply(d: Direction, rotation_deg: f64, mirrored: bool) -> Direction {
    if is_pole(d) {
        return d;
    }
    let phi = if mirrored { -d.phi_deg() } else { d.phi_deg() };
    Direction::from_degrees(d.theta_deg(), phi + rotation_deg)
}

/// The transform taking `rep` to `member` (same class), as (ψ in [0°, 360°), mirrored).
/// Prefers a pure rotation when one exists.
pub fn transform(rep: &Pair, member: &Pair) -> (f64, bool) {
    let w = |x: f64| x.rem_euclid(360.0);
    let (rl, rv, ml, mv) = (rep.light, rep.view, member.light, member.view);
    let psi = if !is_pole(rl) && !is_pole(ml) {
        // light decides ψ unless the signed differences disagree (then mirror)
        let dr = w(rl.phi_deg() - rv.phi_deg());
        let dm = w(ml.phi_deg() - mv.phi_deg());
        let same = is_pole(rv) || {
            let e = w(dr - dm);
            e.min(360.0 - e) < 10.0 * TOLERANCE_DEG
        };
        if same {
            return (w(ml.phi_deg() - rl.phi_deg()), false);
        }
        return (w(ml.phi_deg() + rl.phi_deg()), true);
    } else if !is_pole(rv) {
        w(mv.phi_deg() - rv.phi_deg())
    } else {
        0.0
    };
    (psi, false)
}

#[cfg(test)]
mod tests {
    use super::*;
    use gonio_dataset::sweep::Sweep;
    use gonio_simulator::brdf::BrdfModel;

    #[test]
    fn bonn_classes_and_transforms_reproduce_every_member() {
        let s = Sweep::resolve("bonn81").unwrap();
        let pairs = s.pairs();
        let cls = classes(&pairs);
        assert_eq!(cls.iter().map(Vec::len).sum::<usize>(), 6561);
        // far fewer classes than pairs, and not fewer than the distinct (θ_l, θ_v) cells
        assert!(cls.len() < 6561 / 5 && cls.len() > 36, "{}", cls.len());
        let mut mirrored = 0;
        for c in &cls {
            let rep = &pairs[c[0]];
            for &m in c {
                let member = &pairs[m];
                let (psi, mir) = transform(rep, member);
                mirrored += mir as usize;
                let l = apply(rep.light, psi, mir);
                let v = apply(rep.view, psi, mir);
                assert!(
                    l.angle_to(member.light) < 1e-9 && v.angle_to(member.view) < 1e-9,
                    "rep {rep:?} member {member:?} ψ {psi} mirrored {mir}"
                );
                assert_eq!(key(rep), key(member));
            }
        }
        assert!(mirrored > 0, "the Bonn set has mirror-only equivalents");
        // pairs in different classes really differ in (θ_l, θ_v, |Δφ|)
        let reps: Vec<(f64, f64, f64)> = cls
            .iter()
            .map(|c| {
                let p = &pairs[c[0]];
                (
                    p.light.theta_deg(),
                    p.view.theta_deg(),
                    abs_delta_phi_deg(p.light, p.view),
                )
            })
            .collect();
        for (i, a) in reps.iter().enumerate() {
            for b in &reps[..i] {
                let close = (a.0 - b.0).abs() < 1e-3 && (a.1 - b.1).abs() < 1e-3 && (a.2 - b.2).abs() < 1e-3;
                assert!(!close, "{a:?} and {b:?} should be one class");
            }
        }
    }

    fn model(toml_text: &str) -> BrdfModel {
        toml::from_str(toml_text).unwrap()
    }

    /// Rotation invariance is what "isotropic" means; mirror invariance is what the
    /// reduction additionally uses. Both are checked for every isotropic model family in
    /// the simulator's library; an anisotropic Ward fails the rotation check, so the check
    /// itself discriminates.
    #[test]
    fn isotropic_library_brdfs_are_mirror_symmetric() {
        let iso = [
            "model = \"lambert\"\nalbedo = [0.5, 0.4, 0.3]",
            "model = \"modified-phong\"\nkd = [0.3, 0.3, 0.3]\nks = [0.4, 0.4, 0.4]\nexponent = 30.0",
            "model = \"phong\"\nkd = [0.3, 0.3, 0.3]\nks = [0.4, 0.4, 0.4]\nexponent = 20.0",
            "model = \"blinn-phong\"\nkd = [0.3, 0.3, 0.3]\nks = [0.4, 0.4, 0.4]\nexponent = 50.0",
            "model = \"ward\"\nkd = [0.3, 0.2, 0.1]\nks = [0.1, 0.1, 0.1]\nalpha = 0.2",
            "model = \"oren-nayar\"\nalbedo = [0.6, 0.5, 0.4]\nsigma_deg = 25.0",
            "model = \"rough-plastic\"\ndistribution = \"ggx\"\nalpha = 0.25\neta = 1.5\ndiffuse_reflectance = [0.5, 0.5, 0.5]",
        ];
        let dirs = gonio_dataset::sweep::bonn81();
        let check = |m: &BrdfModel, psi: f64, mirror: bool| -> f64 {
            let mut worst: f64 = 0.0;
            for l in dirs.iter().step_by(3) {
                for v in dirs.iter().step_by(2) {
                    let a = m.eval(l.vector(), v.vector());
                    let b = m.eval(apply(*l, psi, mirror).vector(), apply(*v, psi, mirror).vector());
                    for c in 0..3 {
                        let rel = (a[c] - b[c]).abs() / a[c].abs().max(1e-12);
                        worst = worst.max(rel);
                    }
                }
            }
            worst
        };
        for t in iso {
            let m = model(t);
            for psi in [0.0, 37.0, 90.0, 211.0] {
                assert!(check(&m, psi, false) < 1e-9, "{t}: not rotation invariant at ψ={psi}");
                assert!(check(&m, psi, true) < 1e-9, "{t}: not mirror symmetric at ψ={psi}");
            }
        }
        let aniso =
            model("model = \"ward\"\nkd = [0.3, 0.2, 0.1]\nks = [0.3, 0.3, 0.3]\nalpha_x = 0.08\nalpha_y = 0.4");
        assert!(
            check(&aniso, 37.0, false) > 1e-3,
            "an anisotropic Ward must not pass as isotropic"
        );
    }

    #[test]
    fn pole_pairs_are_one_class_per_theta() {
        let s = Sweep::resolve("bonn81").unwrap();
        let pairs = s.pairs();
        let cls = classes(&pairs);
        // light at the pole, view on the 45° ring: all 18 views are one class
        let first = pairs
            .iter()
            .position(|p| p.light.theta == 0.0 && (p.view.theta_deg() - 45.0).abs() < 1e-9)
            .unwrap();
        let c = cls.iter().find(|c| c.contains(&first)).unwrap();
        assert_eq!(c.len(), 18);
        for &m in c {
            let (psi, mir) = transform(&pairs[first], &pairs[m]);
            assert!(!mir);
            assert!(apply(pairs[first].view, psi, mir).angle_to(pairs[m].view) < 1e-9);
        }
    }
}
