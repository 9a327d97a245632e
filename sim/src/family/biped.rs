//! The biped family: a human-like body in an A-pose with two three-joint arms and legs, and the
//! front/back cues that make its heading observable: a face (nose, jaw), a deeper chest in front,
//! buttocks behind, and feet that point forwards.
//!
//! Coordinates: metres, x forward, y left, z up (ROS REP-103), standing on z ≈ 0.

use nalgebra::{Point3, Vector3};

use super::{Anatomy, BetaParameter};
use crate::implicit::{Body, Part, RoundCone};
use crate::skeleton::Skeleton;

pub const BETA: &[BetaParameter] = &[
    BetaParameter::new("leg_length", 0.70, 1.00, "hip-to-ground height (m)"),
    BetaParameter::new("torso_length", 0.45, 0.65, "pelvis-to-neck distance (m)"),
    BetaParameter::new("hip_width", 0.24, 0.36, "hip breadth (m)"),
    BetaParameter::new("shoulder_width", 0.32, 0.46, "shoulder breadth (m)"),
    BetaParameter::new("chest_girth", 0.10, 0.15, "chest depth radius (m)"),
    BetaParameter::new("waist_girth", 0.085, 0.13, "waist depth radius (m)"),
    BetaParameter::new("arm_length", 0.50, 0.75, "shoulder-to-fingertip length (m)"),
    BetaParameter::new("arm_girth", 0.035, 0.055, "upper-arm radius (m)"),
    BetaParameter::new("leg_girth", 0.055, 0.085, "thigh radius (m), capped by the hip breadth"),
    BetaParameter::new("head_size", 0.085, 0.115, "skull radius (m)"),
    BetaParameter::new("neck_length", 0.05, 0.12, "neck length (m)"),
];

pub fn build(beta: &[f64]) -> Anatomy {
    let [leg_length, torso_length, hip_width, shoulder_width, chest_girth, waist_girth, arm_length, arm_girth, leg_girth, head_size, neck_length] =
        std::array::from_fn(|i| beta[i]);
    let p = |x: f64, y: f64, z: f64| Point3::new(x, y, z);
    let pelvis_height = leg_length + 0.06;

    let mut skeleton = Skeleton::default();
    let mut parts: Vec<Part> = Vec::new();
    let mut mobility = Vec::new();
    let mut joint = |skeleton: &mut Skeleton, name, parent, at: Point3<f64>, how_mobile: f64| {
        mobility.push(how_mobile);
        skeleton.add(name, parent, at)
    };
    let bone = |from: usize, to: Point3<f64>, r0: f64, r1: f64, skeleton: &Skeleton| {
        RoundCone::new(skeleton.joints[from].rest_position, to, r0, r1)
    };

    let pelvis = joint(&mut skeleton, "pelvis", None, p(0.0, 0.0, pelvis_height), 0.0);
    let spine = joint(
        &mut skeleton,
        "spine",
        Some(pelvis),
        p(0.0, 0.0, pelvis_height + 0.35 * torso_length),
        0.6,
    );
    let chest = joint(
        &mut skeleton,
        "chest",
        Some(spine),
        p(0.0, 0.0, pelvis_height + 0.7 * torso_length),
        0.6,
    );
    let neck_base = p(0.0, 0.0, pelvis_height + torso_length);
    let neck = joint(&mut skeleton, "neck", Some(chest), neck_base, 0.8);
    let head_position = neck_base + Vector3::new(0.0, 0.0, neck_length);
    let head = joint(&mut skeleton, "head", Some(neck), head_position, 0.8);

    let hip_lateral = 0.5 * hip_width / (0.9 * waist_girth);
    let chest_lateral = 0.4 * shoulder_width / chest_girth;
    let shape = bone(
        pelvis,
        skeleton.joints[spine].rest_position,
        0.9 * waist_girth,
        waist_girth,
        &skeleton,
    )
    .widened(hip_lateral);
    parts.push(Part { shape, joint: pelvis });
    let shape = bone(
        spine,
        skeleton.joints[chest].rest_position,
        waist_girth,
        chest_girth,
        &skeleton,
    )
    .widened(0.5 * (hip_lateral + chest_lateral));
    parts.push(Part { shape, joint: spine });
    let shape = bone(
        chest,
        neck_base - Vector3::new(0.0, 0.0, 0.5 * chest_girth),
        chest_girth,
        0.8 * chest_girth,
        &skeleton,
    )
    .widened(chest_lateral);
    parts.push(Part { shape, joint: chest });
    let shape = bone(
        neck,
        head_position + Vector3::new(0.0, 0.0, 0.3 * head_size),
        0.45 * head_size,
        0.45 * head_size,
        &skeleton,
    );
    parts.push(Part { shape, joint: neck });
    let skull_bottom = head_position + Vector3::new(0.0, 0.0, 0.9 * head_size);
    let shape = RoundCone::new(
        skull_bottom,
        skull_bottom + Vector3::new(0.02, 0.0, 0.5 * head_size),
        head_size,
        0.95 * head_size,
    );
    parts.push(Part { shape, joint: head });
    // Front/back cues a depth camera can see (a person is otherwise close to symmetric front to
    // back): a face with a nose and jaw jutting forwards, a chest that is deeper in front, and
    // buttocks behind.
    // A cone on the head from `start` along `offset`.
    let on_head = |start: Point3<f64>, offset: Vector3<f64>, r0: f64, r1: f64| Part {
        shape: RoundCone::new(start, start + offset, r0, r1),
        joint: head,
    };
    let face = skull_bottom + Vector3::new(0.6 * head_size, 0.0, -0.1 * head_size);
    // The nose is no thinner than a fingertip: the thinnest part sets the meshing grid.
    let nose_radius = (0.5 * arm_girth).max(0.12 * head_size);
    let nose = Vector3::new(0.5 * head_size, 0.0, -0.15 * head_size);
    parts.push(on_head(face, nose, 0.35 * head_size, nose_radius));
    let chin = skull_bottom + Vector3::new(0.4 * head_size, 0.0, -0.6 * head_size);
    let jaw = Vector3::new(0.45 * head_size, 0.0, -0.1 * head_size);
    parts.push(on_head(chin, jaw, 0.45 * head_size, 0.3 * head_size));
    // A bar across the body (along y) of half-length `half_width` and radius `radius`.
    let across = |centre: Point3<f64>, half_width: f64, radius: f64, joint| Part {
        shape: RoundCone::new(
            centre - Vector3::new(0.0, half_width, 0.0),
            centre + Vector3::new(0.0, half_width, 0.0),
            radius,
            radius,
        ),
        joint,
    };
    let breast = p(0.65 * chest_girth, 0.0, pelvis_height + 0.62 * torso_length);
    parts.push(across(breast, 0.3 * shoulder_width, 0.7 * chest_girth, chest));
    let seat = p(-0.55 * waist_girth, 0.0, pelvis_height - 0.02);
    parts.push(across(seat, 0.25 * hip_width, 0.75 * waist_girth, pelvis));

    let shoulder_height = neck_base.z - 0.6 * chest_girth;
    for side in [1.0f64, -1.0] {
        let names = if side > 0.0 {
            ["left_shoulder", "left_elbow", "left_wrist"]
        } else {
            ["right_shoulder", "right_elbow", "right_wrist"]
        };
        let direction = Vector3::new(0.0, side * 40f64.to_radians().sin(), -(40f64.to_radians().cos()));
        let start = p(0.0, side * (0.5 * shoulder_width - arm_girth), shoulder_height);
        let shoulder = joint(&mut skeleton, names[0], Some(chest), start, 1.2);
        let elbow = joint(
            &mut skeleton,
            names[1],
            Some(shoulder),
            start + 0.45 * arm_length * direction,
            1.2,
        );
        let wrist = joint(
            &mut skeleton,
            names[2],
            Some(elbow),
            start + 0.85 * arm_length * direction,
            0.8,
        );
        let fingertip = start + arm_length * direction;
        parts.push(Part {
            shape: bone(
                shoulder,
                skeleton.joints[elbow].rest_position,
                arm_girth,
                0.8 * arm_girth,
                &skeleton,
            ),
            joint: shoulder,
        });
        parts.push(Part {
            shape: bone(
                elbow,
                skeleton.joints[wrist].rest_position,
                0.8 * arm_girth,
                0.6 * arm_girth,
                &skeleton,
            ),
            joint: elbow,
        });
        parts.push(Part {
            shape: bone(wrist, fingertip, 0.6 * arm_girth, 0.5 * arm_girth, &skeleton),
            joint: wrist,
        });
    }

    let hip_offset = 0.36 * hip_width;
    let thigh_radius = leg_girth.min(0.85 * hip_offset);
    for side in [1.0f64, -1.0] {
        let names = if side > 0.0 {
            ["left_hip", "left_knee", "left_ankle"]
        } else {
            ["right_hip", "right_knee", "right_ankle"]
        };
        let direction = Vector3::new(0.0, side * 5f64.to_radians().sin(), -(5f64.to_radians().cos()));
        let start = p(0.0, side * hip_offset, leg_length);
        let hip = joint(&mut skeleton, names[0], Some(pelvis), start, 1.0);
        let knee = joint(
            &mut skeleton,
            names[1],
            Some(hip),
            start + 0.48 * leg_length * direction,
            1.0,
        );
        let ankle_position = start + 0.93 * leg_length * direction;
        let ankle = joint(&mut skeleton, names[2], Some(knee), ankle_position, 0.6);
        let toe = ankle_position + Vector3::new(0.22 * leg_length, 0.0, -0.04);
        parts.push(Part {
            shape: bone(
                hip,
                skeleton.joints[knee].rest_position,
                thigh_radius,
                0.65 * thigh_radius,
                &skeleton,
            ),
            joint: hip,
        });
        parts.push(Part {
            shape: bone(knee, ankle_position, 0.6 * thigh_radius, 0.4 * thigh_radius, &skeleton),
            joint: knee,
        });
        parts.push(Part {
            shape: bone(ankle, toe, 0.45 * thigh_radius, 0.4 * thigh_radius, &skeleton),
            joint: ankle,
        });
    }

    Anatomy {
        skeleton,
        body: Body {
            parts,
            blend: 0.6 * arm_girth,
        },
        mobility,
    }
}
