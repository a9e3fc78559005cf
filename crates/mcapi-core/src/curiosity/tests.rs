//! Tests of the whole channel, from the expansion to the freeze rules, on
//! the signals of Eq. 6.

use rand_distr::{Distribution, StandardNormal};

use super::channel::module_rng;
use super::sfa::expand;
use super::*;

fn params() -> ValidCuriosityParams {
    CuriosityParams::default()
        .check()
        .expect("defaults are valid")
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-12
}

fn corr(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    sab / (saa * sbb).sqrt()
}

/// |corr(y, slow feature)| of a module, without learning, over the next
/// 160 samples of the source (two periods of sin t at dt = 0.08) from
/// time index `from`.
fn feature_corr(sfa: &SfaModule, source: Eq6Source, from: u64) -> f64 {
    let dt = params().dt;
    let (y, slow): (Vec<f64>, Vec<f64>) = (from..from + 160)
        .map(|k| {
            let t = k as f64 * dt;
            (sfa.output(&Signals::eq6(source, t)), source.slow_feature(t))
        })
        .unzip();
    corr(&y, &slow).abs()
}

/// Trains a lone module on one source for `max` samples; returns the
/// sample count (checked every 10) from which |corr| stays above 0.9.
fn samples_to_corr(source: Eq6Source, seed: u64, max: u64) -> Option<u64> {
    let p = params();
    let mut sfa = SfaModule::random(2, &p, &mut module_rng(seed, 0));
    let mut signals = Signals::with_params(&p);
    let mut first = None;
    for n in 1..=max {
        sfa.learn(&signals.next(source));
        if n % 10 == 0 {
            match (feature_corr(&sfa, source, n) > 0.9, first) {
                (true, None) => first = Some(n),
                (false, Some(_)) => first = None,
                _ => {}
            }
        }
    }
    first
}

/// The alternating visits of the channel tests: `blocks` blocks of `len`
/// samples, book first. Returns the channel and every step.
fn alternate(seed: u64, blocks: usize, len: usize) -> (CuriosityChannel, Vec<CuriosityStep>) {
    let p = params();
    let mut channel = CuriosityChannel::new(2, p.clone(), seed).expect("channel");
    let mut signals = Signals::with_params(&p);
    let mut steps = Vec::with_capacity(blocks * len);
    for block in 0..blocks {
        let source = Eq6Source::ALL[block % 2];
        for _ in 0..len {
            let x = signals.next(source);
            steps.push(channel.observe(source.index(), &x).expect("valid sample"));
        }
    }
    (channel, steps)
}

/// Book samples only, until the first freeze (at most `max`).
fn book_until_freeze(
    channel: &mut CuriosityChannel,
    signals: &mut Signals,
    max: usize,
) -> Vec<CuriosityStep> {
    let mut steps = Vec::new();
    for _ in 0..max {
        let x = signals.next(Eq6Source::Book);
        let step = channel.observe(0, &x).expect("valid sample");
        steps.push(step);
        if step.frozen.is_some() {
            break;
        }
    }
    steps
}

#[test]
fn expansion_is_quadratic_in_the_documented_order() {
    let mut z = Vec::new();
    expand_quadratic(&[2.0, 3.0], &mut z);
    assert_eq!(z, [2.0, 3.0, 4.0, 9.0, 6.0]);
    expand_quadratic(&[1.0, 2.0, 3.0], &mut z);
    assert_eq!(z, [1.0, 2.0, 3.0, 1.0, 4.0, 9.0, 2.0, 3.0, 6.0]);
    assert_eq!(expanded_dim(3), 9);
}

#[test]
fn eq6_signals_on_per_source_clocks() {
    let mut signals = Signals::new(0.08);
    // t = 0: book [0 + 1, 1], music [sin(π/3) − 1, 1].
    assert_eq!(signals.next(Eq6Source::Book), [1.0, 1.0]);
    let m = signals.next(Eq6Source::Music);
    assert!(close(m[0], 3f64.sqrt() / 2.0 - 1.0) && close(m[1], 1.0));
    // The book's clock advanced, the music's did so independently.
    signals.next(Eq6Source::Book);
    assert!(close(signals.time(Eq6Source::Book), 0.16));
    assert!(close(signals.time(Eq6Source::Music), 0.08));
    let t: f64 = 0.7;
    let c = (11.0 * t).cos();
    let b = Signals::eq6(Eq6Source::Book, t);
    assert!(close(b[0], t.sin() + c * c) && close(b[1], c));
}

/// Measured over seeds 0-19 (`measure_eq6`, below): |corr| > 0.9 for
/// good after 20-130 samples of the book (median 65) and 20-200 of the
/// music (median 50). The test allows 300 samples, "a few hundred" as §7
/// says.
#[test]
fn learner_recovers_the_slow_features_of_eq6() {
    for source in Eq6Source::ALL {
        for seed in 0..5 {
            let n = samples_to_corr(source, seed, 300);
            assert!(
                n.is_some(),
                "{source:?}, seed {seed}: no |corr| > 0.9 by 300"
            );
        }
    }
}

#[test]
fn whitening_gives_identity_covariance() {
    let p = params();
    // The book signal (d = 5) and a random 3-dimensional one (d = 9).
    let mut rng = module_rng(11, 0);
    let mut signals = Signals::with_params(&p);
    let book: Vec<Vec<f64>> = (0..500)
        .map(|_| signals.next(Eq6Source::Book).to_vec())
        .collect();
    let noise: Vec<Vec<f64>> = (0..500)
        .map(|_| (0..3).map(|_| StandardNormal.sample(&mut rng)).collect())
        .collect();
    for samples in [book, noise] {
        let m = samples[0].len();
        let mut sfa = SfaModule::random(m, &p, &mut module_rng(1, 0));
        for x in &samples {
            sfa.learn(x);
        }
        // The population covariance of z, computed directly in two passes.
        let zs: Vec<Vec<f64>> = samples.iter().map(|x| expand(x)).collect();
        let d = zs[0].len();
        let n = zs.len() as f64;
        let mean: Vec<f64> = (0..d)
            .map(|i| zs.iter().map(|z| z[i]).sum::<f64>() / n)
            .collect();
        let mut cov = vec![0.0; d * d];
        for z in &zs {
            for i in 0..d {
                for j in 0..d {
                    cov[i * d + j] += (z[i] - mean[i]) * (z[j] - mean[j]) / n;
                }
            }
        }
        for (a, b) in sfa.mean().iter().zip(&mean) {
            assert!((a - b).abs() < 1e-9, "running mean {a} vs {b}");
        }
        for (a, b) in sfa.covariance().iter().zip(&cov) {
            assert!((a - b).abs() < 1e-9, "running covariance {a} vs {b}");
        }
        // Cov of S(z − m) over the samples = S C S ≈ I (no eigenvalue of
        // these signals is under the floor).
        let white = sfa.whitened_covariance();
        for i in 0..d {
            for j in 0..d {
                let want = if i == j { 1.0 } else { 0.0 };
                let got = white[i * d + j];
                assert!(
                    (got - want).abs() < 1e-6,
                    "m = {m}: (S C S)[{i},{j}] = {got}"
                );
            }
        }
    }
}

#[test]
fn roc_rules_by_hand() {
    // N_max = 3, β = 0.01.
    let mut roc = Roc::new(3, 0.01);
    let c = |v: f64, w: f64| Centre {
        value: v,
        weight: w,
    };
    // y = 0: no centre, e = 0; add (0, 1).
    assert_eq!(roc.update(0.0), 0.0);
    assert_eq!(roc.centres(), [c(0.0, 1.0)]);
    // y = 1: e = 1 before the update; (0,1) → weight 2, v += ½(1 − 0); add (1,1).
    assert_eq!(roc.update(1.0), 1.0);
    assert_eq!(roc.centres(), [c(0.5, 2.0), c(1.0, 1.0)]);
    // y = 4: nearest (1,1), e = 3 → (2.5, 2); add (4,1).
    assert_eq!(roc.update(4.0), 3.0);
    assert_eq!(roc.centres(), [c(0.5, 2.0), c(2.5, 2.0), c(4.0, 1.0)]);
    // y = 10: nearest (4,1), e = 6 → (7, 2); three centres exist, so the
    // closest pair 0.5, 2.5 merges into (1.5, 4); add (10, 1).
    assert_eq!(roc.update(10.0), 6.0);
    assert_eq!(roc.centres(), [c(1.5, 4.0), c(7.0, 2.0), c(10.0, 1.0)]);
    // y = 2: nearest (1.5,4), e = 0.5 → weight 5, v = 1.5 + 0.5/5 = 1.6;
    // merge 7 and 10: (7·2 + 10·1)/3 = 8, weight 3; add (2, 1).
    assert_eq!(roc.update(2.0), 0.5);
    let got = roc.centres();
    assert_eq!(got.len(), 3);
    assert!(close(got[0].value, 1.6) && got[0].weight == 5.0);
    assert!(close(got[1].value, 8.0) && got[1].weight == 3.0);
    assert_eq!(got[2], c(2.0, 1.0));

    // β bounds the step below: a centre of weight 199 that wins moves by
    // max(1/200, 0.01) = 0.01 of the way, not 1/200.
    let mut heavy = Roc::new(3, 0.01);
    heavy.centres.push(c(0.0, 199.0));
    assert_eq!(heavy.update(1.0), 1.0);
    assert!(close(heavy.centres()[0].value, 0.01));
    assert_eq!(heavy.centres()[0].weight, 200.0);
}

#[test]
fn estimation_error_and_eq7_by_hand() {
    let p = params();
    let mut progress = LearningProgress::new(&p);
    assert_eq!(progress.epsilon(), 1.0);
    // Zero errors into a window of 1.0s: ε_n = 1 − n/20, and with the lag
    // history at 1.0, ξ_n = 800 (n/20)/20 = 2n, clipped at 12.
    let mut xi = Vec::new();
    for n in 1..=40u32 {
        let (eps, x) = progress.push(0.0, &p);
        if n <= 20 {
            assert!(close(eps, 1.0 - f64::from(n) / 20.0), "ε_{n} = {eps}");
        }
        xi.push(x);
    }
    for (n, &x) in xi.iter().enumerate().take(5) {
        assert!(close(x, 2.0 * (n + 1) as f64), "ξ_{} = {x}", n + 1);
    }
    // Past n = 20 the window is all zeros, ε_n = 0, and ξ_n = 40 ε_{n−20}
    // = 2(40 − n): clipped up to n = 34, then 10, 8, 6, 4, 2, 0.
    assert!(xi[5..34].iter().all(|&x| x == 12.0), "{xi:?}");
    for n in 35..=40 {
        assert!(
            close(xi[n - 1], 2.0 * (40 - n) as f64),
            "ξ_{n} = {}",
            xi[n - 1]
        );
    }
    // A growing error is no progress: clipped at 0.
    let (_, x) = progress.push(1.0, &p);
    assert_eq!(x, 0.0);
}

#[test]
fn curiosity_is_positive_while_learning_and_zero_once_frozen() {
    let p = params();
    let mut channel = CuriosityChannel::new(2, p.clone(), 3).expect("channel");
    let mut signals = Signals::with_params(&p);
    let steps = book_until_freeze(&mut channel, &mut signals, 1000);
    let frozen_at = steps.len();
    // Measured: seeds 0-19 freeze after 117-216 book samples.
    assert!(frozen_at <= 300, "no freeze within 300 samples");
    assert_eq!(steps[frozen_at - 1].frozen, Some(0));
    // Learning: every early sample is rewarding, a stretch at the clip.
    assert!(steps[..20].iter().all(|s| s.learned && s.xi_cur > 0.0));
    assert!(steps.iter().filter(|s| s.xi_cur == p.clip).count() >= 10);
    assert!(steps.iter().all(|s| s.explained_by.is_none() && s.learned));
    // Frozen: the book is explained; more of it gives 0 and trains nothing.
    assert_eq!(channel.module_count(), 1);
    assert_eq!(channel.library()[0].source(), 0);
    assert!(channel.all_explained());
    for _ in 0..500 {
        let step = channel
            .observe(0, &signals.next(Eq6Source::Book))
            .expect("valid");
        assert_eq!(step.xi_cur, 0.0);
        assert!(!step.learned && step.explained_by == Some(0) && step.all_explained);
    }
    assert_eq!(channel.active().learned_samples(), 0);
    // A new signal is interesting again: the fresh module binds to it.
    let step = channel
        .observe(1, &signals.next(Eq6Source::Music))
        .expect("valid");
    assert!(step.learned && step.xi_cur > 0.0 && !step.all_explained);
    assert_eq!(channel.active().source(), Some(1));
}

/// Measured over seeds 0-19 (`measure_eq6`, 8000 alternating samples):
/// the own-source window mean of a frozen module stays ≤ 0.161, the
/// other source's ≥ 0.385 in 19 seeds; in one (seed 7) the music
/// module's window on the book dips once to 0.295 (harmless there, as
/// the book module explains the book first).
#[test]
fn a_frozen_module_explains_its_own_signal_and_not_the_other() {
    for seed in 0..3 {
        let (channel, _) = alternate(seed, 4, 400);
        assert_eq!(channel.module_count(), 2, "seed {seed}");
        for module in channel.library() {
            let own = module.source();
            let other = 1 - own;
            let mean_own = module.window_mean(own).expect("own window");
            let mean_other = module.window_mean(other).expect("other window");
            assert!(module.samples_of(other) >= 20);
            assert!(mean_own <= 0.3, "seed {seed}: own {mean_own}");
            assert!(mean_other > 0.3, "seed {seed}: other {mean_other}");
            assert_eq!(
                channel
                    .explained_by(own)
                    .map(|i| channel.library()[i].source()),
                Some(own)
            );
        }
    }
    // The book module alone, before any music module exists.
    let p = params();
    let mut channel = CuriosityChannel::new(2, p.clone(), 0).expect("channel");
    let mut signals = Signals::with_params(&p);
    book_until_freeze(&mut channel, &mut signals, 1000);
    for _ in 0..40 {
        channel
            .observe(1, &signals.next(Eq6Source::Music))
            .expect("valid");
    }
    let book = &channel.library()[0];
    assert!(book.window_mean(0).expect("own") <= 0.3);
    assert!(book.window_mean(1).expect("music") > 0.3);
    assert_eq!(channel.explained_by(1), None);
}

/// Measured over seeds 0-19 (`measure_eq6`) with 400-sample visits: the
/// book module freezes at sample 117-216, the music module at 518-693
/// (i.e. after 118-293 music samples); no other freeze and no ξ_cur > 0
/// after the second in 8000 samples. The frozen features correlate
/// 0.993-1.000 with sin t, resp. sin(2t + π/3).
#[test]
fn the_channel_learns_both_sources_on_alternating_visits_deterministically() {
    let (channel, steps) = alternate(5, 10, 400);
    let freezes: Vec<(usize, usize)> = steps
        .iter()
        .enumerate()
        .filter_map(|(n, s)| s.frozen.map(|k| (n + 1, k)))
        .collect();
    assert_eq!(freezes.len(), 2, "{freezes:?}");
    let last_freeze = freezes[1].0;
    assert!(last_freeze <= 2000, "{freezes:?}");
    let library = channel.library();
    assert_eq!((library[0].source(), library[1].source()), (0, 1));
    assert_eq!(library[0].frozen_at() as usize, freezes[0].0);
    assert_eq!(library[1].frozen_at() as usize, last_freeze);
    assert!(channel.all_explained());
    assert!(
        steps[last_freeze..]
            .iter()
            .all(|s| s.xi_cur == 0.0 && !s.learned && s.all_explained)
    );
    // Every sample that went unexplained at the start of a block of the
    // other source (while bound to the book) gave 0.
    assert!(steps.iter().all(|s| s.learned || s.xi_cur == 0.0));

    // Deterministic for a seed, and exactly resumable from a snapshot.
    let (again, steps_again) = alternate(5, 10, 400);
    assert_eq!(steps, steps_again);
    assert_eq!(channel, again);
    let json = serde_json::to_string(&channel).expect("serialise");
    let restored: CuriosityChannel = serde_json::from_str(&json).expect("deserialise");
    assert_eq!(restored, channel);
    let (other_seed, _) = alternate(6, 10, 400);
    assert_ne!(other_seed.library()[0].sfa(), channel.library()[0].sfa());
}

#[test]
fn observe_rejects_bad_samples() {
    let mut channel = CuriosityChannel::new(2, params(), 0).expect("channel");
    assert!(channel.observe(0, &[1.0]).is_err());
    assert!(channel.observe(0, &[1.0, f64::NAN]).is_err());
    assert!(channel.observe(0, &[1.0, 1e13]).is_err());
    assert!(channel.observe(64, &[1.0, 1.0]).is_err());
    assert_eq!(channel.samples(), 0);
    assert!(
        !channel.all_explained(),
        "nothing is explained before any sample"
    );
    assert!(CuriosityChannel::new(0, params(), 0).is_err());
}

#[test]
fn params_are_checked() {
    assert!(CuriosityParams::default().check().is_ok());
    let cases = [
        CuriosityParams {
            max_centres: 1,
            ..Default::default()
        },
        CuriosityParams {
            beta: 0.0,
            ..Default::default()
        },
        CuriosityParams {
            tau: 0,
            ..Default::default()
        },
        CuriosityParams {
            eta_c: f64::NAN,
            ..Default::default()
        },
        CuriosityParams {
            gain: -1.0,
            ..Default::default()
        },
        CuriosityParams {
            dt: 0.0,
            ..Default::default()
        },
        CuriosityParams {
            max_sources: 0,
            ..Default::default()
        },
    ];
    for case in cases {
        assert!(case.check().is_err(), "{case:?}");
    }
    let partial: CuriosityParams =
        serde_json::from_str(r#"{"gain": 400}"#).expect("partial params parse");
    assert_eq!(partial.gain, 400.0);
    assert_eq!(partial.tau, 20);
}

/// The numbers quoted in the docs above:
/// `cargo test --lib curiosity::tests::measure_eq6 -- --ignored --nocapture`.
#[test]
#[ignore = "a measurement, not a check"]
fn measure_eq6() {
    for source in Eq6Source::ALL {
        let n: Vec<_> = (0..20)
            .map(|seed| samples_to_corr(source, seed, 2000))
            .collect();
        eprintln!("{source:?}: samples to |corr| > 0.9 for good: {n:?}");
    }
    for seed in 0..20 {
        let p = params();
        let mut channel = CuriosityChannel::new(2, p.clone(), seed).expect("channel");
        let mut signals = Signals::with_params(&p);
        let book = book_until_freeze(&mut channel, &mut signals, 5000).len();
        let (channel, steps) = alternate(seed, 20, 400);
        let freezes: Vec<usize> = steps
            .iter()
            .enumerate()
            .filter_map(|(n, s)| s.frozen.map(|_| n + 1))
            .collect();
        let last_xi = steps.iter().rposition(|s| s.xi_cur > 0.0).map(|n| n + 1);
        // Window means over the run, from each module's 20th sample on.
        let (mut own_max, mut other_min) = (0.0f64, f64::INFINITY);
        let mut replay = CuriosityChannel::new(2, p.clone(), seed).expect("channel");
        let mut signals = Signals::with_params(&p);
        for block in 0..20 {
            let source = Eq6Source::ALL[block % 2];
            for _ in 0..400 {
                replay
                    .observe(source.index(), &signals.next(source))
                    .expect("valid");
                for module in replay.library() {
                    if module.samples_of(source.index()) >= 20 {
                        let w = module.window_mean(source.index()).unwrap_or(f64::NAN);
                        if module.source() == source.index() {
                            own_max = own_max.max(w);
                        } else {
                            other_min = other_min.min(w);
                        }
                    }
                }
            }
        }
        let corr: Vec<f64> = channel
            .library()
            .iter()
            .map(|m| {
                let source = Eq6Source::ALL[m.source()];
                feature_corr(m.sfa(), source, 0)
            })
            .collect();
        eprintln!(
            "seed {seed}: book alone freezes at {book}; alternating: freezes {freezes:?}, \
             last ξ > 0 at {last_xi:?}, own max {own_max:.3}, other min {other_min:.3}, \
             |corr| of frozen features {corr:.3?}"
        );
    }
}
