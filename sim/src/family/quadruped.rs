//! The quadruped family: a dog-like body with a neck, head, four three-segment legs and a tail.
//!
//! Coordinates: metres, x forward, y left, z up (ROS REP-103), standing on z ≈ 0.

use nalgebra::{Point3, Vector3};

use super::{Anatomy, BetaParameter};
use crate::implicit::{Body, Part, RoundCone};
use crate::skeleton::Skeleton;

pub const BETA: &[BetaParameter] = &[
    BetaParameter::new("torso_length", 0.45, 0.90, "pelvis-to-chest distance ×1/0.7 (m)"),
    BetaParameter::new("torso_girth", 0.10, 0.18, "torso radius at mid-spine (m)"),
    BetaParameter::new(
        "chest_to_rump_ratio",
        0.85,
        1.25,
        "front torso radius / rear torso radius",
    ),
    BetaParameter::new("leg_length", 0.30, 0.60, "shoulder-to-ground height (m)"),
    BetaParameter::new("leg_girth_ratio", 0.30, 0.45, "thigh radius / torso girth"),
    BetaParameter::new("neck_length", 0.10, 0.28, "neck length (m)"),
    BetaParameter::new("head_length", 0.14, 0.28, "skull-to-snout length (m)"),
    BetaParameter::new("head_girth", 0.055, 0.10, "skull radius (m)"),
    BetaParameter::new("tail_length", 0.10, 0.50, "tail length (m)"),
    BetaParameter::new("snout_taper", 0.35, 0.70, "snout-tip radius / skull radius"),
];

pub fn build(beta: &[f64]) -> Anatomy {
    let [torso_length, girth, chest_ratio, leg_length, leg_girth_ratio, neck_length, head_length, head_girth, tail_length, snout_taper] =
        std::array::from_fn(|i| beta[i]);
    let rear_radius = 2.0 * girth / (1.0 + chest_ratio);
    let front_radius = rear_radius * chest_ratio;
    let spine_height = leg_length + 0.35 * girth;
    let p = |x: f64, y: f64, z: f64| Point3::new(x, y, z);

    let mut skeleton = Skeleton::default();
    let mut parts = Vec::new();
    let mut mobility = Vec::new();
    let mut joint = |skeleton: &mut Skeleton, name, parent, at: Point3<f64>, how_mobile: f64| {
        mobility.push(how_mobile);
        skeleton.add(name, parent, at)
    };

    let pelvis = joint(
        &mut skeleton,
        "pelvis",
        None,
        p(-0.35 * torso_length, 0.0, spine_height),
        0.0,
    );
    let spine = joint(&mut skeleton, "spine", Some(pelvis), p(0.0, 0.0, spine_height), 0.5);
    let chest = joint(
        &mut skeleton,
        "chest",
        Some(spine),
        p(0.35 * torso_length, 0.0, spine_height),
        0.5,
    );
    let neck_base = p(0.5 * torso_length, 0.0, spine_height + 0.15 * girth);
    let neck = joint(&mut skeleton, "neck", Some(chest), neck_base, 1.0);
    let neck_direction = Vector3::new(55f64.to_radians().cos(), 0.0, 55f64.to_radians().sin());
    let head_position = neck_base + neck_length * neck_direction;
    let head = joint(&mut skeleton, "head", Some(neck), head_position, 1.0);
    let snout_direction = Vector3::new(0.94, 0.0, -0.34).normalize();

    let bone = |from: usize, to: Point3<f64>, r0: f64, r1: f64, skeleton: &Skeleton| Part {
        shape: RoundCone::new(skeleton.joints[from].rest_position, to, r0, r1),
        joint: from,
    };
    parts.push(bone(
        pelvis,
        skeleton.joints[spine].rest_position,
        rear_radius,
        girth,
        &skeleton,
    ));
    parts.push(bone(
        spine,
        skeleton.joints[chest].rest_position,
        girth,
        front_radius,
        &skeleton,
    ));
    parts.push(bone(chest, neck_base, front_radius, 0.9 * front_radius, &skeleton));
    parts.push(bone(
        neck,
        head_position,
        0.55 * front_radius,
        0.85 * head_girth,
        &skeleton,
    ));
    parts.push(bone(
        head,
        head_position + head_length * snout_direction,
        head_girth,
        snout_taper * head_girth,
        &skeleton,
    ));

    let leg_radius = leg_girth_ratio * girth;
    let lateral = 0.7 * girth;
    for (names, x, parent) in [
        (
            ["front_left_shoulder", "front_left_elbow", "front_left_wrist"],
            0.38 * torso_length,
            chest,
        ),
        (
            ["front_right_shoulder", "front_right_elbow", "front_right_wrist"],
            0.38 * torso_length,
            chest,
        ),
        (
            ["hind_left_hip", "hind_left_knee", "hind_left_ankle"],
            -0.38 * torso_length,
            pelvis,
        ),
        (
            ["hind_right_hip", "hind_right_knee", "hind_right_ankle"],
            -0.38 * torso_length,
            pelvis,
        ),
    ] {
        let y = if names[0].contains("left") { lateral } else { -lateral };
        let top = joint(
            &mut skeleton,
            names[0],
            Some(parent),
            p(x, y, spine_height - 0.1 * girth),
            1.0,
        );
        let middle = joint(&mut skeleton, names[1], Some(top), p(x, y, 0.55 * leg_length), 1.0);
        let bottom = joint(&mut skeleton, names[2], Some(middle), p(x, y, 0.12 * leg_length), 0.7);
        let toe = p(x + 0.12 * leg_length, y, 0.04 * leg_length);
        parts.push(bone(
            top,
            skeleton.joints[middle].rest_position,
            leg_radius,
            0.75 * leg_radius,
            &skeleton,
        ));
        parts.push(bone(
            middle,
            skeleton.joints[bottom].rest_position,
            0.7 * leg_radius,
            0.55 * leg_radius,
            &skeleton,
        ));
        parts.push(bone(bottom, toe, 0.55 * leg_radius, 0.5 * leg_radius, &skeleton));
    }

    let tail_radius = (0.3 * rear_radius).max(0.025);
    let tail_direction = Vector3::new(-(35f64.to_radians().cos()), 0.0, -(35f64.to_radians().sin()));
    let tail_start = p(
        -0.35 * torso_length - 0.7 * rear_radius,
        0.0,
        spine_height + 0.3 * rear_radius,
    );
    let segment = tail_length / 3.0;
    let tail_base = joint(&mut skeleton, "tail_base", Some(pelvis), tail_start, 1.5);
    let tail_middle = joint(
        &mut skeleton,
        "tail_middle",
        Some(tail_base),
        tail_start + segment * tail_direction,
        1.5,
    );
    let tail_end = joint(
        &mut skeleton,
        "tail_end",
        Some(tail_middle),
        tail_start + 2.0 * segment * tail_direction,
        1.5,
    );
    let tip = tail_start + 3.0 * segment * tail_direction;
    parts.push(bone(
        tail_base,
        skeleton.joints[tail_middle].rest_position,
        tail_radius,
        0.85 * tail_radius,
        &skeleton,
    ));
    parts.push(bone(
        tail_middle,
        skeleton.joints[tail_end].rest_position,
        0.85 * tail_radius,
        0.7 * tail_radius,
        &skeleton,
    ));
    parts.push(bone(tail_end, tip, 0.7 * tail_radius, 0.55 * tail_radius, &skeleton));

    Anatomy {
        skeleton,
        body: Body {
            parts,
            blend: 0.35 * leg_radius,
        },
        mobility,
    }
}
