//! Anatomy that makes heading observable: joint limits every sampled pose and the gait keep, and
//! front/back cues that tell a subject from itself turned half a turn.

use gdvae_sim::family::{Family, JointLimit, PoseMode, Subject};
use gdvae_sim::mesh::Mesh;
use gdvae_sim::motion::gait_theta;
use gdvae_sim::seeds;
use nalgebra::Vector3;
use rand::Rng;

/// Every joint rotation of `theta` within its family's limit; the names of those that are not.
fn broken_limits(subject: &Subject, theta: &[f64]) -> Vec<String> {
    (1..subject.skeleton.len())
        .filter_map(|joint| {
            let name = subject.skeleton.joints[joint].name;
            let rotation = Vector3::from_column_slice(&theta[3 * (joint - 1)..3 * joint]);
            let limit = subject.family.joint_limit(name);
            (!limit.holds(&rotation, &subject.skeleton.limb_axis(joint)))
                .then(|| format!("{name} {rotation:?} {limit:?}"))
        })
        .collect()
}

#[test]
fn every_sampled_pose_and_the_gait_keep_the_joint_limits() {
    for family in Family::ALL {
        let subject = Subject::with_vertex_count(family, family.sample_beta(&mut seeds::rng(3)), 2500).unwrap();
        let mut rng = seeds::rng(11);
        for mode in [PoseMode::Gaussian, PoseMode::Bent] {
            for _ in 0..300 {
                let theta = subject.sample_theta(mode, &mut rng);
                let broken = broken_limits(&subject, &theta);
                assert!(broken.is_empty(), "{family:?} {mode:?}: {broken:?}");
            }
        }
        for step in 0..64 {
            let theta = gait_theta(&subject.skeleton, family, step as f64 / 64.0);
            let broken = broken_limits(&subject, &theta);
            assert!(broken.is_empty(), "{family:?} gait: {broken:?}");
        }
        // Hinges do bend, and only one way.
        let hinges: Vec<usize> = (1..subject.skeleton.len())
            .filter(|&j| {
                matches!(
                    family.joint_limit(subject.skeleton.joints[j].name),
                    JointLimit::Hinge { .. }
                )
            })
            .collect();
        assert!(hinges.len() >= 4, "{family:?}: knees and elbows are hinges");
    }
}

/// `count` points on `mesh`'s surface, area-weighted, centred on their bounding box.
fn surface_sample(mesh: &Mesh, count: usize, seed: u64) -> Vec<Vector3<f64>> {
    let mut rng = seeds::rng(seed);
    let areas: Vec<f64> = mesh
        .triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| mesh.positions[i as usize]);
            0.5 * (b - a).cross(&(c - a)).norm()
        })
        .collect();
    let total: f64 = areas.iter().sum();
    let mut cumulative = Vec::with_capacity(areas.len());
    let mut running = 0.0;
    for a in &areas {
        running += a / total;
        cumulative.push(running);
    }
    let mut points: Vec<Vector3<f64>> = (0..count)
        .map(|_| {
            let u: f64 = rng.random();
            let t = cumulative.partition_point(|c| *c < u).min(areas.len() - 1);
            let [a, b, c] = mesh.triangles[t].map(|i| mesh.positions[i as usize]);
            let (mut s, mut r): (f64, f64) = (rng.random(), rng.random());
            if s + r > 1.0 {
                (s, r) = (1.0 - s, 1.0 - r);
            }
            (a + s * (b - a) + r * (c - a)).coords
        })
        .collect();
    let low = points.iter().fold(Vector3::repeat(f64::INFINITY), |m, p| m.inf(p));
    let high = points.iter().fold(Vector3::repeat(f64::NEG_INFINITY), |m, p| m.sup(p));
    let centre = 0.5 * (low + high);
    points.iter_mut().for_each(|p| *p -= centre);
    points
}

fn chamfer(a: &[Vector3<f64>], b: &[Vector3<f64>]) -> f64 {
    let one_way = |from: &[Vector3<f64>], to: &[Vector3<f64>]| {
        from.iter()
            .map(|p| to.iter().map(|q| (p - q).norm_squared()).fold(f64::INFINITY, f64::min))
            .sum::<f64>()
            / from.len() as f64
    };
    one_way(a, b) + one_way(b, a)
}

#[test]
fn a_subject_is_told_from_itself_turned_half_a_turn() {
    for family in Family::ALL {
        for seed in 0..3 {
            let subject =
                Subject::with_vertex_count(family, family.sample_beta(&mut seeds::rng(40 + seed)), 3000).unwrap();
            let a = surface_sample(&subject.rest_mesh, 1500, 1);
            let b = surface_sample(&subject.rest_mesh, 1500, 2);
            let turned: Vec<Vector3<f64>> = b.iter().map(|p| Vector3::new(-p.x, -p.y, p.z)).collect();
            let floor = chamfer(&a, &b);
            let half_turn = chamfer(&a, &turned);
            // Above the hips, centred on its own box (what a camera sees of a person behind a
            // table; the feet no longer shift the centre).
            let upper = |points: &[Vector3<f64>]| {
                let kept: Vec<Vector3<f64>> = points.iter().filter(|p| p.z > 0.0).copied().collect();
                let low = kept.iter().fold(Vector3::repeat(f64::INFINITY), |m, p| m.inf(p));
                let high = kept.iter().fold(Vector3::repeat(f64::NEG_INFINITY), |m, p| m.sup(p));
                let centre = 0.5 * (low + high);
                kept.into_iter().map(|p| p - centre).collect::<Vec<_>>()
            };
            let upper_floor = chamfer(&upper(&a), &upper(&b));
            let upper_turned = chamfer(&upper(&a), &upper(&turned));
            eprintln!(
                "{family:?} subject {seed}: half turn / floor = {:.1} whole, {:.1} upper half",
                half_turn / floor,
                upper_turned / upper_floor
            );
            assert!(
                half_turn > 3.0 * floor,
                "{family:?} subject {seed}: turned {half_turn:.2e} vs resampling floor {floor:.2e}"
            );
            // A person's feet alone would pass the first check: the upper body must tell too
            // (the face, chest and seat; before them this ratio was 1.2-2.0 for these subjects).
            if family == Family::Biped {
                assert!(
                    upper_turned > 2.2 * upper_floor,
                    "biped subject {seed} above the hips: turned {upper_turned:.2e} vs floor {upper_floor:.2e}"
                );
            }
        }
    }
}
