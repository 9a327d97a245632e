//! Several objects in one stream (`track::association`): synthetic tracks whose answers are known
//! (paths that cross, an occlusion, a return, a glimpse), and the Hungarian assignment itself.

use gdvae_node::bundle::UNCALIBRATED_Z_I_SPREAD;
use gdvae_node::track::association::{assign, Associated, AssociationSettings, Associator, Candidate, TrackEvent};
use gdvae_node::track::TrackSettings;

/// The default settings in model units for a bundle of the assumed z_I spread (as the pipeline
/// turns them for a bundle): the z_I codes below are written at that scale.
fn model_units() -> AssociationSettings {
    TrackSettings::default().in_model_units(UNCALIBRATED_Z_I_SPREAD).objects
}

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
        points: 0,
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
    let mut a = Associator::new(model_units());
    let frames = run(&mut a, 60, |f| vec![candidate(0.02 * f as f32, 0.0, 0)]);
    assert_eq!(frames[0].ids, vec![None], "tentative at first");
    assert_eq!(frames[1].ids, vec![None]);
    assert_eq!(frames[2].events, vec![TrackEvent::Born { id: 1 }]);
    assert!(frames[2..].iter().all(|f| f.ids == vec![Some(1)]));
    assert!(frames[3..].iter().all(|f| f.events.is_empty()));
}

#[test]
fn a_glimpse_of_one_frame_never_becomes_an_object() {
    let mut a = Associator::new(model_units());
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
    let mut a = Associator::new(model_units());
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
    let mut a = Associator::new(model_units());
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
    let mut a = Associator::new(model_units());
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
    let mut a = Associator::new(model_units());
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
                points: 0,
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

/// `ObjectTracks`: each confirmed track has filters of its own, fed only by its own candidates,
/// and a track that returns within the memory window goes on from the filters it had.
#[test]
fn each_track_keeps_its_own_filters_and_gets_them_back_when_it_returns() {
    use gdvae_node::track::ObjectTracks;
    let settings = TrackSettings::default().in_model_units(UNCALIBRATED_Z_I_SPREAD);
    let mut tracks = ObjectTracks::new(&settings);
    let log_variance = vec![-4.0f32; 8];
    let mut fused: std::collections::HashMap<u64, u64> = std::collections::HashMap::new();
    let mut ids_seen = Vec::new();
    // 2 s of two objects apart; object 1 gone from 2 s to 4 s (past lost_s = 1 s); back until 5 s.
    for f in 0..150usize {
        let t = f as f64 / FPS;
        let mut scene = vec![candidate(-1.0, 0.0, 0)];
        if !(2.0..4.0).contains(&t) {
            scene.push(candidate(1.0, 0.0, 1));
        }
        let (tracked, _) = tracks.associate(t, &scene);
        for c in &tracked {
            let z = &scene[c.candidate].z_i;
            let filters = tracks.filters(c.id);
            filters.update(
                (z, &log_variance),
                ([1.0, 0.0, 0.0, 0.0], None),
                &[0.0; 4],
                scene[c.candidate].centre,
                c.dt,
            );
            assert!(c.dt > 0.0 && c.dt <= 1.0, "a frame's dt: {}", c.dt);
            // A track's fused z_I is its own object's: the two never mix.
            let mean = filters.shape.mean();
            assert!((mean[0] - z[0]).abs() < 1e-3, "track {} fused {mean:?} for {z:?}", c.id);
            *fused.entry(c.id).or_default() = filters.shape.frames_fused();
            if !ids_seen.contains(&c.id) {
                ids_seen.push(c.id);
            }
        }
    }
    assert_eq!(
        ids_seen.len(),
        2,
        "two objects, two ids (the returning one got its own back)"
    );
    // Object 0 in every frame but its birth's; object 1 in 2 s + 1 s of frames, less a birth each
    // time: 84 frames fused if its filters came back with its id, 27 had it started afresh.
    let mut counts: Vec<u64> = fused.values().copied().collect();
    counts.sort_unstable();
    assert!(counts[1] >= 145, "{fused:?}");
    assert!(
        counts[0] >= 80,
        "the returning track's filters went on from where they were: {fused:?}"
    );
}

/// Two objects of one kind walk side by side, merge into one cluster (twice the points) for half a
/// second and part: neither track takes the merged cluster (both coast), and each gets its own
/// object back after, not the other's; with the merge check off, one track takes the merged
/// cluster and follows it to the wrong side.
#[test]
fn two_tracks_coast_through_a_merge_and_keep_their_objects() {
    let run_with = |merge_ratio: f32| {
        let mut associator = Associator::new(AssociationSettings {
            merge_ratio,
            ..model_units()
        });
        // Both move along +x at 1 m/s, 0.9 m apart in y; from 1 s to 1.5 s one merged cluster at
        // their middle, with the points of both.
        let frames = run(&mut associator, 90, |f| {
            let t = f as f64 / FPS;
            let x = t as f32;
            let same_shape = |y: f32, points: usize| Candidate {
                centre: [x, y, 0.4],
                z_i: z_i(0),
                points,
            };
            if (1.0..1.5).contains(&t) {
                vec![same_shape(0.45, 1000)]
            } else {
                vec![same_shape(0.0, 500), same_shape(0.9, 520)]
            }
        });
        let before = &frames[29].ids;
        let after = &frames[89].ids;
        let merged_ids: Vec<Option<u64>> = frames[30..45].iter().flat_map(|f| f.ids.clone()).collect();
        (before.clone(), after.clone(), merged_ids)
    };
    let (before, after, merged) = run_with(1.4);
    assert!(before[0].is_some() && before[1].is_some());
    assert_eq!(before, after, "each object has its own track again after the merge");
    assert!(
        merged.iter().all(Option::is_none),
        "nobody takes the merged cluster: {merged:?}"
    );
    let (_, _, merged_off) = run_with(0.0);
    assert!(
        merged_off.iter().any(Option::is_some),
        "without the check a track takes it"
    );
}

/// A piece split from an object (an arm, 0.3 m from its body) in some frames starts no track of its
/// own; with `fragment_m = 0` it becomes one.
#[test]
fn a_piece_of_an_object_starts_no_track() {
    let tracks_seen = |fragment_m: f32| {
        let mut associator = Associator::new(AssociationSettings {
            fragment_m,
            ..model_units()
        });
        let frames = run(&mut associator, 60, |f| {
            let mut c = vec![candidate(0.0, 0.0, 0)];
            if f >= 10 {
                c.push(Candidate {
                    centre: [0.3, 0.1, 0.9],
                    z_i: vec![-1.0; 8],
                    points: 0,
                });
            }
            c
        });
        let mut ids: Vec<u64> = frames.iter().flat_map(|f| f.ids.iter().flatten().copied()).collect();
        ids.sort_unstable();
        ids.dedup();
        ids
    };
    assert_eq!(tracks_seen(0.5), vec![1], "the object alone");
    assert_eq!(tracks_seen(0.0), vec![1, 2], "the piece its own track");
}

/// One subject leaves; the other walks on 1.1 m from where it was. The leaving subject's track,
/// coasting with its gate widening, must not take the remaining subject's candidate from that
/// subject's own track.
#[test]
fn a_coasting_track_does_not_take_another_tracks_object() {
    let mut associator = Associator::new(model_units());
    let frames = run(&mut associator, 90, |f| {
        let t = f as f32 / FPS as f32;
        let mut c = vec![candidate(0.5 * t, 0.0, 0)];
        if f < 30 {
            c.push(candidate(0.5 * t, 1.1, 2));
        }
        c
    });
    let first = frames[20].ids[0];
    assert!(first.is_some());
    assert!(
        frames[30..].iter().all(|f| f.ids[0] == first),
        "the remaining subject keeps its id"
    );
}

/// An object whose legs another hides for a third of a second: its cluster's centre rises 0.42 m
/// (a biped behind a passing quadruped in the crossing benchmark), more than a gate (0.3 m, as
/// config/objects.toml, plus a frame's 2.5 m/s), but moves little across the ground. Distances on
/// the ground plane keep it on its track.
#[test]
fn an_object_whose_centre_rises_as_its_legs_are_hidden_keeps_its_track() {
    let mut associator = Associator::new(AssociationSettings {
        gate_m: 0.3,
        ..model_units()
    });
    let frames = run(&mut associator, 60, |f| {
        let hidden = (20..30).contains(&f);
        let mut c = candidate(0.01 * f as f32, 0.0, 0);
        c.centre[2] = if hidden { 0.82 } else { 0.4 };
        vec![c]
    });
    let ids: Vec<_> = frames.iter().map(|f| f.ids.clone()).collect();
    assert!(ids[5..].iter().all(|ids| ids == &vec![Some(1)]), "{ids:?}");
}

/// Two objects merge into one cluster that loses points as one passes behind the other (from both
/// objects' points to 1.2 times one's): once recognised as merged it stays so until they part, and
/// neither track is pulled to the cluster's centre.
#[test]
fn a_merged_cluster_that_loses_points_stays_merged_until_the_objects_part() {
    let mut associator = Associator::new(model_units());
    let frames = run(&mut associator, 90, |f| {
        let t = f as f64 / FPS;
        let x = t as f32;
        let at = |y: f32, points: usize| Candidate {
            centre: [x, y, 0.4],
            z_i: z_i(0),
            points,
        };
        match t {
            t if (1.0..1.2).contains(&t) => vec![at(0.45, 1000)],
            t if (1.2..1.5).contains(&t) => vec![at(0.45, 620)],
            _ => vec![at(0.0, 500), at(0.9, 520)],
        }
    });
    let merged: Vec<Option<u64>> = frames[30..45].iter().flat_map(|f| f.ids.clone()).collect();
    assert!(
        merged.iter().all(Option::is_none),
        "nobody takes the merged cluster: {merged:?}"
    );
    assert_eq!(frames[29].ids, frames[89].ids, "each object on its own track after");
    assert!(frames[29].ids.iter().all(Option::is_some));
}

/// An object coming back into view a part at a time: its first frames' z_I lie beyond
/// `reid_distance` of its own (1.27 against 1.0) but within reach. It waits for its z_I to come
/// within `reid_distance` and gets its old id; without the wait it is taken for a new object.
#[test]
fn an_object_coming_back_into_view_in_part_waits_for_its_shape_and_gets_its_id_back() {
    let run_with = |reid_wait_s: f64| {
        let mut associator = Associator::new(AssociationSettings {
            reid_wait_s,
            ..model_units()
        });
        let frames = run(&mut associator, 150, |f| {
            let t = f as f64 / FPS;
            let mut c = vec![candidate(0.0, -1.0, 0)];
            if !(1.0..3.0).contains(&t) {
                let mut returning = candidate(1.0, 1.0, 1);
                if (3.0..3.2).contains(&t) {
                    returning.z_i.iter_mut().for_each(|v| *v += 0.45);
                }
                c.push(returning);
            }
            c
        });
        frames.iter().flat_map(|f| f.events.clone()).collect::<Vec<_>>()
    };
    let waited = run_with(0.5);
    assert!(
        matches!(waited.last(), Some(TrackEvent::Reidentified { id: 2, .. })),
        "{waited:?}"
    );
    let hasty = run_with(0.0);
    assert_eq!(hasty.last(), Some(&TrackEvent::Born { id: 3 }), "{hasty:?}");
}

/// Object 1 leaves; while its track coasts (its gate widening), object 0's cluster splits into its
/// body and its legs for a few frames. The coasting track does not take the legs (a piece of the
/// object track 1 holds: taking it would move the track onto object 0); without `fragment_m` it
/// does.
#[test]
fn a_coasting_track_does_not_take_a_piece_of_an_object_another_track_holds() {
    let run_with = |fragment_m: f32| {
        let mut associator = Associator::new(AssociationSettings {
            fragment_m,
            ..model_units()
        });
        let frames = run(&mut associator, 60, |f| {
            let t = f as f64 / FPS;
            let x = 0.3 * t as f32;
            let body = |points: usize| Candidate {
                centre: [x, 0.0, 0.8],
                z_i: z_i(0),
                points,
            };
            match t {
                t if t < 1.0 => vec![body(1000), candidate(0.5, 0.8, 0)],
                t if (1.5..1.6).contains(&t) => vec![
                    body(700),
                    Candidate {
                        centre: [x + 0.1, 0.1, 0.4],
                        z_i: z_i(0),
                        points: 300,
                    },
                ],
                _ => vec![body(1000)],
            }
        });
        (
            frames[45..48].iter().map(|f| f.ids.clone()).collect::<Vec<_>>(),
            frames[59].ids.clone(),
        )
    };
    let (split, end) = run_with(0.5);
    assert!(split.iter().all(|ids| ids == &vec![Some(1), None]), "{split:?}");
    assert_eq!(end, vec![Some(1)]);
    let (split, _) = run_with(0.0);
    assert!(
        split.iter().any(|ids| ids.contains(&Some(2))),
        "without the rule it takes the legs: {split:?}"
    );
}

/// The z_I distances are given in z_I spreads: a bundle whose z_I is twice as wide (its
/// calibration's z_I_spread twice the assumed) gets twice the distances in model units, and a
/// returning object whose z_I moved by the same share of the spread gets its id back alike; taken
/// in the narrower bundle's units, the same return is a new object.
#[test]
fn z_i_distances_follow_the_bundle_s_z_i_spread() {
    let returns = |width: f32, spread: f32| {
        let mut associator = Associator::new(TrackSettings::default().in_model_units(spread).objects);
        let moved = 2.0 + 0.8 / 8f32.sqrt(); // 0.8 of the assumed bundle's z_I units away
        let frames = run(&mut associator, 240, |f| {
            let t = f as f64 / FPS;
            let mut c = vec![Candidate {
                centre: [0.0, -1.0, 0.4],
                z_i: vec![0.0; 8],
                points: 0,
            }];
            if !(2.0..5.0).contains(&t) {
                let code = if t < 2.0 { 2.0 } else { moved };
                c.push(Candidate {
                    centre: [1.0, 1.0, 0.4],
                    z_i: vec![width * code; 8],
                    points: 0,
                });
            }
            c
        });
        frames.iter().flat_map(|f| f.events.clone()).collect::<Vec<_>>()
    };
    let back = |events: &[TrackEvent]| {
        events
            .iter()
            .any(|e| matches!(e, TrackEvent::Reidentified { id: 2, .. }))
    };
    assert!(back(&returns(1.0, UNCALIBRATED_Z_I_SPREAD)));
    assert!(back(&returns(2.0, 2.0 * UNCALIBRATED_Z_I_SPREAD)));
    let narrow = returns(2.0, UNCALIBRATED_Z_I_SPREAD);
    assert!(
        !back(&narrow) && narrow.contains(&TrackEvent::Born { id: 3 }),
        "{narrow:?}"
    );
}
