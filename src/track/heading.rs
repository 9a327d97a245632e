//! Heading tracker: the subject's yaw about +z filtered over time from two measurements.
//!
//! - The encoder's yaw, every frame: noisy, and for near-symmetric bodies sometimes the back taken
//!   for the front, now and then wild. It measures the angle (front or back, whichever it more
//!   likely read; noisier when the frame's yaw copies disagree) and votes once per frame on which
//!   way is forward (`heading_encoder_vote`).
//! - The direction of motion of the object's centre, when it moves faster than a threshold: a
//!   walking subject faces where it goes. It measures the angle and votes on the sense: as much
//!   as an encoder frame, and `heading_walk_vote` once the centre has gone somewhere
//!   (`motion_walk_travel_m`), since the centre of a body turning in place also sweeps about.
//!
//! The angle and its rate are a Kalman filter whose turn rate fades unless the readings renew it
//! (`heading_rate_time_s`; 0: a constant-turn-rate model). The encoder's yaw is read as a
//! mixture: the front as the track has it, the back taken for the front (`heading_back_share`), or
//! a wild reading at any angle (`heading_wild_share`). A reading is used as the more likely of the
//! first two, weighted by how likely it is to be that rather than wild, so a reading near 90
//! degrees off, which fits neither, moves the track little instead of pulling it towards the back.
//! The motion's direction, far outside its expected spread, is down-weighted (Huber). So a burst of
//! bad frames bends the track little. The sense (front or back) is a log-odds accumulated from the
//! votes and clamped: the track turns by 180 degrees only when the evidence against it outweighs
//! what it has gathered, never because of one frame. The votes count in time, not in frames (a
//! frame at 10 Hz votes as three at 30 Hz), so a burst of wrong readings is resisted, and the track
//! comes back after one, in the same time whatever the camera's rate. Everything is causal: each
//! estimate uses the frames up to it.

use std::collections::VecDeque;
use std::f64::consts::{FRAC_PI_2, PI, TAU};

use super::settings::TrackSettings;

/// Vote per frame of motion that has not gone anywhere yet on the sense (log-odds units; a walk
/// votes `heading_walk_vote`, an encoder frame `heading_encoder_vote`).
const MOTION_VOTE: f64 = 1.0;
/// Sense evidence a new track starts with: a few contrary frames may still turn it round.
const INITIAL_SENSE: f64 = 1.0;
/// Motion measurements beyond this many standard deviations of their innovation are down-weighted.
const HUBER_SIGMAS: f64 = 2.5;
/// Least weight of an encoder reading (its variance is divided by the weight).
const MIN_ENCODER_WEIGHT: f64 = 1e-3;
/// Rate uncertainty of a new track (rad/s).
const INITIAL_RATE_STD: f64 = 1.0;
/// Time constant of the running mean of the encoder's frame-to-frame jitter (s): an encoder that
/// scatters more than `heading_std_deg` says gets a wider noise.
const JITTER_TIME_S: f64 = 1.0;
/// The frame rate at which the votes count as given (`heading_encoder_vote`, `MOTION_VOTE`): at
/// other rates a frame counts for its share of a second at this rate, so the track resists a burst
/// of wrong readings, and comes back after one, in the same time whatever the camera's rate. (An
/// encoder's errors depend on the view, and the view changes with time, not with frames.)
const VOTE_RATE_HZ: f64 = 30.0;
/// Most a single frame counts, in frames at `VOTE_RATE_HZ` (after a gap in the stream).
const MAX_FRAME_WEIGHT: f64 = 3.0;

/// `angle` wrapped to (-pi, pi].
fn wrap(angle: f64) -> f64 {
    let w = angle.rem_euclid(TAU);
    if w > PI {
        w - TAU
    } else {
        w
    }
}

/// `angle` wrapped to (-pi/2, pi/2]: the difference of two axes.
fn wrap_axial(angle: f64) -> f64 {
    let w = angle.rem_euclid(PI);
    if w > FRAC_PI_2 {
        w - PI
    } else {
        w
    }
}

/// What the tracker says after a frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Heading {
    /// Filtered yaw (radians, unwrapped: continuous over turns).
    pub yaw: f64,
    /// Its standard deviation (radians).
    pub yaw_std: f64,
    /// Turn rate (rad/s).
    pub rate: f64,
    /// The motion direction used this frame, if the object moved fast enough.
    pub motion_yaw: Option<f64>,
    /// Sense evidence (log-odds that forward is right); the track turned round this frame if it
    /// went below zero.
    pub sense: f64,
    pub turned_round: bool,
}

/// Velocity of the object's centre: least-squares slope of the positions over a sliding window,
/// given only when the motion is steady: each half of the window moves at least
/// `STEADY_SPEED_SHARE` of the threshold speed, and the two halves' directions differ by less than
/// `STEADY_MAX_TURN`. The centre of a partial view jumps when the visible part of a body changes;
/// over a window such a jump looks like a walk, but it lies in one half (or between them, where
/// neither half moves). And a walk goes somewhere: over `TRAVEL_WINDOWS` windows the centre must
/// have travelled `min_travel` (the mean position of the horizon's last quarter from that of its
/// first). The centre of the visible points of a subject that turns in place, its limbs shifting,
/// sweeps back and forth by up to half a metre at walking speed for a second at a time; it comes
/// back, where a walk does not.
#[derive(Debug, Clone)]
struct Motion {
    window_s: f64,
    min_speed: f64,
    min_travel: f64,
    /// A motion that travelled this far over the horizon is a walk: it votes `walk_vote`.
    walk_travel: f64,
    samples: VecDeque<(f64, f64, f64)>,
}

/// The motion of the centre in one frame: its direction and whether it is a walk that went
/// somewhere (travelled `motion_walk_travel_m`).
#[derive(Debug, Clone, Copy)]
struct Moved {
    velocity: (f64, f64),
    walked: bool,
}

/// The travel test's horizon, in motion windows.
const TRAVEL_WINDOWS: f64 = 2.0;

/// Least speed of each half of the motion window, as a share of the threshold speed.
const STEADY_SPEED_SHARE: f64 = 0.5;
/// Most angle between the directions of the two halves of the motion window (radians: 45 deg).
const STEADY_MAX_TURN: f64 = std::f64::consts::FRAC_PI_4;

impl Motion {
    /// A new position: the walk's velocity if there is one.
    fn push(&mut self, t: f64, x: f64, y: f64) -> Option<Moved> {
        self.samples.push_back((t, x, y));
        let horizon = self.horizon_s();
        while self.samples.front().is_some_and(|(t0, _, _)| t - t0 > horizon) {
            self.samples.pop_front();
        }
        let window = self.samples.iter().filter(|s| t - s.0 <= self.window_s);
        let span = t - window.clone().next()?.0;
        if window.clone().count() < 4 || span < 0.6 * self.window_s {
            return None;
        }
        let velocity = slope(window.clone())?;
        let middle = t - span / 2.0;
        let first = slope(window.clone().filter(|s| s.0 <= middle))?;
        let second = slope(window.filter(|s| s.0 > middle))?;
        let least = STEADY_SPEED_SHARE * self.min_speed;
        let turn = wrap(first.1.atan2(first.0) - second.1.atan2(second.0)).abs();
        let steady = first.0.hypot(first.1) >= least && second.0.hypot(second.1) >= least && turn < STEADY_MAX_TURN;
        if !steady {
            return None;
        }
        // Before the samples span the travel test's horizon, the window's tests alone decide.
        let travel = self.travel(t);
        let gate = self.min_travel <= 0.0 || travel.is_none_or(|d| d >= self.min_travel);
        let walked = self.walk_travel > 0.0 && travel.is_some_and(|d| d >= self.walk_travel);
        gate.then_some(Moved { velocity, walked })
    }

    /// How long the samples are kept (s).
    fn horizon_s(&self) -> f64 {
        TRAVEL_WINDOWS * self.window_s
    }

    /// How far the centre travelled over the horizon (m): None before the samples span most of it.
    fn travel(&self, t: f64) -> Option<f64> {
        let horizon = self.horizon_s();
        let &(start, _, _) = self.samples.front()?;
        if t - start < 0.8 * horizon {
            return None;
        }
        let mean = |keep: &dyn Fn(f64) -> bool| {
            let (n, x, y) = self
                .samples
                .iter()
                .filter(|s| keep(s.0))
                .fold((0.0, 0.0, 0.0), |(n, x, y), s| (n + 1.0, x + s.1, y + s.2));
            (x / n, y / n)
        };
        let (x0, y0) = mean(&|time| time <= start + horizon / 4.0);
        let (x1, y1) = mean(&|time| time >= t - horizon / 4.0);
        Some((x1 - x0).hypot(y1 - y0))
    }
}

/// Least-squares slope (vx, vy) of positions over time; None for fewer than 2 samples or no spread
/// in time (a half window at a low frame rate may hold only 2).
fn slope<'a>(samples: impl Iterator<Item = &'a (f64, f64, f64)> + Clone) -> Option<(f64, f64)> {
    let n = samples.clone().count();
    if n < 2 {
        return None;
    }
    let n = n as f64;
    let mean_t = samples.clone().map(|s| s.0).sum::<f64>() / n;
    let mean_x = samples.clone().map(|s| s.1).sum::<f64>() / n;
    let mean_y = samples.clone().map(|s| s.2).sum::<f64>() / n;
    let stt: f64 = samples.clone().map(|s| (s.0 - mean_t).powi(2)).sum();
    if stt <= 0.0 {
        return None;
    }
    let vx = samples.clone().map(|s| (s.0 - mean_t) * (s.1 - mean_x)).sum::<f64>() / stt;
    let vy = samples.map(|s| (s.0 - mean_t) * (s.2 - mean_y)).sum::<f64>() / stt;
    Some((vx, vy))
}

#[derive(Debug, Clone)]
pub struct HeadingFilter {
    measurement_var: f64,
    accel_var: f64,
    from_motion: bool,
    min_speed: f64,
    motion_var: f64,
    max_sense: f64,
    encoder_vote: f64,
    copy_spread_scale: f64,
    walk_vote: f64,
    rate_time_s: f64,
    /// The encoder's reading as a mixture: shares of wild readings and of back-for-front ones.
    wild_share: f64,
    back_share: f64,
    motion: Motion,
    /// yaw, rate, covariance [[yy, yr], [ry, rr]], sense log-odds.
    state: Option<([f64; 2], [[f64; 2]; 2], f64)>,
    time: f64,
    /// Running mean of the squared axial difference between consecutive encoder yaws (rad^2):
    /// twice the encoder's noise variance, measured without reference to the track (so a track
    /// that went astray cannot talk itself into ignoring the encoder).
    jitter_power: f64,
    previous_encoder_yaw: Option<f64>,
}

impl HeadingFilter {
    pub fn new(settings: &TrackSettings) -> Self {
        Self {
            measurement_var: (settings.heading_std_deg as f64).to_radians().powi(2),
            accel_var: (settings.heading_accel_std as f64).powi(2),
            from_motion: settings.heading_from_motion,
            min_speed: settings.motion_min_speed_mps as f64,
            motion_var: (settings.motion_heading_std_deg as f64).to_radians().powi(2),
            max_sense: settings.heading_flip_evidence as f64,
            encoder_vote: settings.heading_encoder_vote as f64,
            copy_spread_scale: settings.heading_copy_spread_scale as f64,
            walk_vote: settings.heading_walk_vote as f64,
            rate_time_s: settings.heading_rate_time_s as f64,
            wild_share: settings.heading_wild_share as f64,
            back_share: settings.heading_back_share as f64,
            motion: Motion {
                window_s: settings.motion_window_s as f64,
                min_speed: settings.motion_min_speed_mps as f64,
                min_travel: settings.motion_min_travel_m as f64,
                walk_travel: settings.motion_walk_travel_m as f64,
                samples: VecDeque::new(),
            },
            state: None,
            time: 0.0,
            jitter_power: 2.0 * (settings.heading_std_deg as f64).to_radians().powi(2),
            previous_encoder_yaw: None,
        }
    }

    /// Forget the track (a new object): the next frame starts a new one. Motion history is kept,
    /// it belongs to whatever is in view.
    pub fn reset(&mut self) {
        self.state = None;
    }

    /// One frame: the encoder's yaw (radians), the object's centre (m, gravity frame) and the time
    /// since the previous frame (s).
    pub fn update(&mut self, encoder_yaw: f64, centre: [f64; 2], dt: f64) -> Heading {
        self.update_read(encoder_yaw, None, centre, dt)
    }

    /// `update`, with the scatter of the encoder's yaw copies about its reading this frame
    /// (radians; `Encoding::yaw_spread`) when there are copies: a reading its copies disagree on
    /// moves the track less (its noise is widened by `heading_copy_spread_scale` times the scatter).
    pub fn update_read(&mut self, encoder_yaw: f64, copy_spread: Option<f64>, centre: [f64; 2], dt: f64) -> Heading {
        self.time += dt;
        // What this frame counts for, in frames at the votes' rate (a stream without usable stamps
        // gets the nominal rate's dt, so this is 1 at 30 Hz).
        let frame_weight = (dt * VOTE_RATE_HZ).clamp(0.0, MAX_FRAME_WEIGHT);
        if let Some(previous) = self.previous_encoder_yaw {
            let step = wrap_axial(encoder_yaw - previous);
            let weight = (dt / JITTER_TIME_S).clamp(0.0, 1.0);
            self.jitter_power += weight * (step * step - self.jitter_power);
        }
        self.previous_encoder_yaw = Some(encoder_yaw);
        let moved = self.motion.push(self.time, centre[0], centre[1]);
        let motion = moved.and_then(
            |Moved {
                 velocity: (vx, vy),
                 walked,
             }| {
                let speed = vx.hypot(vy);
                // Slower motion points less surely: the spread grows as the speed nears the threshold.
                (self.from_motion && speed >= self.min_speed).then(|| {
                    (
                        vy.atan2(vx),
                        self.motion_var * (2.0 * self.min_speed / speed).max(1.0).powi(2),
                        if walked { self.walk_vote } else { MOTION_VOTE },
                    )
                })
            },
        );
        let (mut x, mut p, mut sense) = match self.state {
            Some(s) => s,
            None => {
                // Start where the motion points if it does (the encoder may face backwards), else
                // where the encoder points.
                let start = motion.map(|(m, _, _)| m).unwrap_or(encoder_yaw);
                let start = start + TAU * ((encoder_yaw - start) / TAU).round();
                let state = (
                    [start, 0.0],
                    [[self.measurement_var, 0.0], [0.0, INITIAL_RATE_STD.powi(2)]],
                    INITIAL_SENSE,
                );
                self.state = Some(state);
                return self.heading(state, motion.map(|(m, _, _)| m), false);
            }
        };
        // Predict: the turn rate kept, or fading with `heading_rate_time_s` (a body turns for a
        // moment, and a track that trusts poor readings less must not coast on an old rate),
        // and white angular acceleration.
        let a = if self.rate_time_s > 0.0 {
            (-dt / self.rate_time_s).exp()
        } else {
            1.0
        };
        x[0] += x[1] * dt;
        x[1] *= a;
        let (dt2, dt3, dt4) = (dt * dt, dt * dt * dt, dt * dt * dt * dt);
        let p00 = p[0][0] + dt * (p[1][0] + p[0][1]) + dt2 * p[1][1] + self.accel_var * dt4 / 4.0;
        let p01 = a * (p[0][1] + dt * p[1][1]) + self.accel_var * dt3 / 2.0;
        let p11 = a * a * p[1][1] + self.accel_var * dt2;
        p = [[p00, p01], [p01, p11]];

        // Sense votes, then turn round if the evidence says the track faces backwards.
        // An encoder that scatters widely is a weaker witness of front and back too.
        let encoder_agrees = wrap(encoder_yaw - x[0]).abs() < FRAC_PI_2;
        let vote = frame_weight * self.encoder_vote * (self.measurement_var / self.encoder_variance());
        sense += if encoder_agrees { vote } else { -vote };
        if let Some((m, _, vote)) = motion {
            let vote = frame_weight * vote;
            sense += if wrap(m - x[0]).abs() < FRAC_PI_2 { vote } else { -vote };
        }
        let mut turned_round = false;
        if sense < 0.0 {
            x[0] += PI;
            sense = -sense;
            turned_round = true;
        }
        sense = sense.min(self.max_sense);

        // Measurements: the encoder's reading, then the motion's direction (when it agrees on
        // sense). The encoder's noise: as configured, or wider when it jitters more from frame to
        // frame (an encoder that cannot tell this body's heading scatters over all angles), and
        // wider still this frame by its yaw copies' scatter. (Only the angle: the copies' scatter
        // in the votes too lost on the choice sets, docs/tracking.md "The yaw copies' scatter".)
        let encoder_var = self.encoder_variance() + (self.copy_spread_scale * copy_spread.unwrap_or(0.0)).powi(2);
        let (innovation, weight) = self.encoder_reading(x[0], p[0][0], encoder_yaw, encoder_var);
        Self::kalman(&mut x, &mut p, innovation, encoder_var / weight.max(MIN_ENCODER_WEIGHT));
        if let Some((m, variance, _)) = motion {
            let innovation = wrap(m - x[0]);
            if innovation.abs() < FRAC_PI_2 {
                Self::correct(&mut x, &mut p, innovation, variance);
            }
        }
        let state = (x, p, sense);
        self.state = Some(state);
        self.heading(state, motion.map(|(m, _, _)| m), turned_round)
    }

    /// The encoder's noise variance now: the configured one, or half its recent jitter if larger.
    fn encoder_variance(&self) -> f64 {
        self.measurement_var.max(self.jitter_power / 2.0)
    }

    /// The encoder's reading of a track at `yaw` (variance `yaw_var`) as (innovation, weight): the
    /// innovation to the front, or to the back if the reading more likely took the back for the
    /// front, and the probability that it is that and not a wild reading.
    fn encoder_reading(&self, yaw: f64, yaw_var: f64, encoder_yaw: f64, encoder_var: f64) -> (f64, f64) {
        let spread = yaw_var + encoder_var;
        let front = wrap(encoder_yaw - yaw);
        let back = wrap(front - PI);
        // Log-likelihoods of the two readings, less their common factor (1 - wild share) times the
        // normal density's normalizer: in logs, so that neither underflows far from the track.
        let log_front = (1.0 - self.back_share).ln() - 0.5 * front * front / spread;
        let log_back = self.back_share.ln() - 0.5 * back * back / spread;
        let (innovation, best, other) = if log_front >= log_back {
            (front, log_front, log_back)
        } else {
            (back, log_back, log_front)
        };
        // Wild readings' density (uniform on the circle) over the chosen reading's.
        let wild = if self.wild_share > 0.0 {
            self.wild_share / TAU * (TAU * spread).sqrt() / (1.0 - self.wild_share) * (-best).exp()
        } else {
            0.0
        };
        (innovation, 1.0 / (1.0 + (other - best).exp() + wild))
    }

    /// Kalman update of the angle with a robustly weighted scalar innovation.
    fn correct(x: &mut [f64; 2], p: &mut [[f64; 2]; 2], innovation: f64, variance: f64) {
        let spread = p[0][0] + variance;
        let standardized = innovation.abs() / spread.sqrt();
        let variance = if standardized > HUBER_SIGMAS {
            // Huber: beyond the threshold the measurement counts as if it were that far.
            variance * (standardized / HUBER_SIGMAS).powi(2)
        } else {
            variance
        };
        Self::kalman(x, p, innovation, variance);
    }

    /// Kalman update of the angle with a scalar innovation of the given variance.
    fn kalman(x: &mut [f64; 2], p: &mut [[f64; 2]; 2], innovation: f64, variance: f64) {
        let s = p[0][0] + variance;
        let k = [p[0][0] / s, p[1][0] / s];
        x[0] += k[0] * innovation;
        x[1] += k[1] * innovation;
        let p00 = (1.0 - k[0]) * p[0][0];
        let p01 = (1.0 - k[0]) * p[0][1];
        let p11 = p[1][1] - k[1] * p[0][1];
        *p = [[p00, p01], [p01, p11]];
    }

    fn heading(&self, state: ([f64; 2], [[f64; 2]; 2], f64), motion_yaw: Option<f64>, turned_round: bool) -> Heading {
        let (x, p, sense) = state;
        Heading {
            yaw: x[0],
            yaw_std: p[0][0].max(0.0).sqrt(),
            rate: x[1],
            motion_yaw,
            sense,
            turned_round,
        }
    }
}
