//! Several objects in one stream (`track::association`): synthetic tracks whose answers are known
//! (paths that cross, an occlusion, a return, a glimpse), and the Hungarian assignment itself.

use gdvae_node::track::association::{assign, Associated, AssociationSettings, Associator, Candidate, TrackEvent};

const FPS: f64 = 30.0;

/// Two shape codes far apart (as two animals of different families), and one near the first.
fn z_i(which: usize) -> Vec<f32> {
    match which {
        0 => vec![0.0; 8],
        1 => vec![2.0; 8],
        _ => vec![0.05; 8],
    }
}

fn candidate(x: f32, y: f32, which: usize) -> Candidate {
    Candidate {
        centre: [x, y, 0.4],
        z_i: z_i(which),
    }
}

/// Runs `frames` frames of `scene(frame) -> candidates`; returns each frame's result.
fn run(associator: &mut Associator, frames: usize, scene: impl Fn(usize) -> Vec<Candidate>) -> Vec<Associated> {
    (0..frames)
        .map(|f| associator.update(f as f64 / FPS, &scene(f)))
        .collect()
}

#[test]
fn the_hungarian_assignment_is_the_least_total_cost_and_never_takes_an_impossible_pair() {
    let inf = f64::INFINITY;
    // Greedy would take (0, 0) at 1.0 and leave row 1 with 10: total 11; the best is 2 + 2.
    let pairs = assign(&[vec![1.0, 2.0], vec![2.0, 10.0]]);
    assert_eq!(sorted(pairs), vec![(0, 1), (1, 0)]);
    // Rectangular both ways, and an impossible pair left out rather than forced.
    assert_eq!(sorted(assign(&[vec![5.0, 1.0, 3.0]])), vec![(0, 1)]);
    assert_eq!(sorted(assign(&[vec![5.0], vec![1.0], vec![3.0]])), vec![(1, 0)]);
    assert_eq!(sorted(assign(&[vec![inf, 1.0], vec![inf, 2.0]])), vec![(0, 1)]);
    assert!(assign(&[vec![inf]]).is_empty());
    assert!(assign(&[]).is_empty());
}

fn sorted(mut pairs: Vec<(usize, usize)>) -> Vec<(usize, usize)> {
    pairs.sort();
    pairs
}

#[test]
fn one_object_is_born_after_the_birth_frames_and_keeps_its_id() {
    let mut a = Associator::new(AssociationSettings::default());
    let frames = run(&mut a, 60, |f| vec![candidate(0.02 * f as f32, 0.0, 0)]);
    assert_eq!(frames[0].ids, vec![None], "tentative at first");
    assert_eq!(frames[1].ids, vec![None]);
    assert_eq!(frames[2].events, vec![TrackEvent::Born { id: 1 }]);
    assert!(frames[2..].iter().all(|f| f.ids == vec![Some(1)]));
    assert!(frames[3..].iter().all(|f| f.events.is_empty()));
}

#[test]
fn a_glimpse_of_one_frame_never_becomes_an_object() {
    let mut a = Associator::new(AssociationSettings::default());
    let frames = run(&mut a, 30, |f| {
        let mut c = vec![candidate(0.0, 0.0, 0)];
        if f == 10 || f == 20 {
            c.push(candidate(1.5, 1.5, 1));
        }
        c
    });
    let born: Vec<_> = frames.iter().flat_map(|f| f.events.clone()).collect();
    assert_eq!(born, vec![TrackEvent::Born { id: 1 }]);
    assert_eq!(a.confirmed(), vec![1]);
}

#[test]
fn two_objects_whose_paths_cross_keep_their_ids() {
    // Head on along x at 1.2 m/s, through the same point at frame 45: position alone cannot tell
    // them apart there, their shapes and their motion can.
    let mut a = Associator::new(AssociationSettings::default());
    let frames = run(&mut a, 90, |f| {
        let x = -1.8 + 1.2 * f as f32 / FPS as f32;
        vec![candidate(x, 0.0, 0), candidate(-x, 0.05, 1)]
    });
    let first = frames[2].ids.clone();
    assert!(first.iter().all(Option::is_some) && first[0] != first[1], "{first:?}");
    for (f, frame) in frames.iter().enumerate().skip(2) {
        assert_eq!(frame.ids, first, "frame {f}: an id switch");
    }
    // The same with two objects of one family (shapes nearly equal): the motion model carries them.
    let mut a = Associator::new(AssociationSettings::default());
    let frames = run(&mut a, 90, |f| {
        let x = -1.8 + 1.2 * f as f32 / FPS as f32;
        vec![candidate(x, 0.0, 0), candidate(-x, 0.05, 2)]
    });
    let first = frames[2].ids.clone();
    assert!(
        frames.iter().skip(2).all(|frame| frame.ids == first),
        "same family: an id switch"
    );
}

#[test]
fn an_object_hidden_for_half_a_second_comes_back_on_its_track() {
    let mut a = Associator::new(AssociationSettings::default());
    let frames = run(&mut a, 90, |f| {
        let x = -1.0 + 0.8 * f as f32 / FPS as f32;
        if (40..55).contains(&f) {
            vec![] // behind another object
        } else {
            vec![candidate(x, 0.0, 0)]
        }
    });
    assert!(frames[55..].iter().all(|f| f.ids == vec![Some(1)]));
    let events: Vec<_> = frames.iter().flat_map(|f| f.events.clone()).collect();
    assert_eq!(events, vec![TrackEvent::Born { id: 1 }], "no end, no new id");
}

#[test]
fn an_object_that_leaves_and_returns_gets_its_id_back_and_a_stranger_does_not() {
    let mut a = Associator::new(AssociationSettings::default());
    // Object 0 (id 1) stays; object 1 (id 2) leaves at 2 s, returns at 5 s elsewhere; at 7 s a
    // third object of another shape arrives.
    let frames = run(&mut a, 300, |f| {
        let t = f as f64 / FPS;
        let mut c = vec![candidate(0.0, -1.0, 0)];
        if !(2.0..5.0).contains(&t) {
            c.push(candidate(if t < 2.0 { 1.0 } else { -1.0 }, 1.0, 1));
        }
        if t >= 7.0 {
            c.push(Candidate {
                centre: [2.0, 2.0, 0.4],
                z_i: vec![-3.0; 8],
            });
        }
        c
    });
    let events: Vec<_> = frames.iter().flat_map(|f| f.events.clone()).collect();
    assert_eq!(events[..2], [TrackEvent::Born { id: 1 }, TrackEvent::Born { id: 2 }]);
    assert_eq!(events[2], TrackEvent::Ended { id: 2 }, "{events:?}");
    match events[3] {
        TrackEvent::Reidentified { id: 2, away_s } => assert!((away_s - 3.1).abs() < 0.1, "{away_s}"),
        other => panic!("expected id 2 back, got {other:?} ({events:?})"),
    }
    assert_eq!(events[4..], [TrackEvent::Born { id: 3 }]);
    assert_eq!(frames[299].ids, vec![Some(1), Some(2), Some(3)]);
}

#[test]
fn settings_are_checked_by_name() {
    assert!(AssociationSettings::default().validate().is_ok());
    let bad = AssociationSettings {
        birth_frames: 0,
        ..Default::default()
    };
    assert!(bad.validate().unwrap_err().contains("birth_frames"));
    let bad = AssociationSettings {
        gate_m: f32::NAN,
        ..Default::default()
    };
    assert!(bad.validate().unwrap_err().contains("gate_m"));
}
