//! The channel (§7, ours): the active module and the library of frozen
//! ones, with the freeze, explain and bind rules, turning a raw signal into
//! the curiosity stimulus ξ_cur.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::params::{MAX_LIBRARY, MAX_SIGNAL_DIM, ValidCuriosityParams, bad};
use super::progress::{ErrorWindow, LearningProgress};
use super::roc::Roc;
use super::sfa::SfaModule;
use crate::error::{AlgoError, MAX_STIMULUS, Result};

/// The module currently learning: IncSFA, ROC, ε and its lag history, the
/// source it is bound to, and the freeze counter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActiveModule {
    sfa: SfaModule,
    roc: Roc,
    progress: LearningProgress,
    /// The source of its first unexplained sample (bind rule).
    source: Option<usize>,
    /// Consecutive learned samples with ε < δ.
    below: u32,
}

/// What one learned sample did to the active module.
struct Learned {
    y: f64,
    epsilon: f64,
    xi: f64,
}

impl ActiveModule {
    fn fresh(m: usize, params: &ValidCuriosityParams, rng: &mut impl Rng) -> Self {
        Self {
            sfa: SfaModule::random(m, params, rng),
            roc: Roc::with_params(params),
            progress: LearningProgress::new(params),
            source: None,
            below: 0,
        }
    }

    /// Steps 1-5 and Eq. 7 on one sample of its source.
    fn learn(&mut self, x: &[f64], params: &ValidCuriosityParams) -> Learned {
        let y = self.sfa.learn(x);
        let error = self.roc.update(y);
        let (epsilon, xi) = self.progress.push(error, params);
        if epsilon < params.delta {
            self.below = self.below.saturating_add(1);
        } else {
            self.below = 0;
        }
        Learned { y, epsilon, xi }
    }

    /// ε of this module.
    pub fn estimation_error(&self) -> f64 {
        self.progress.epsilon()
    }

    /// Samples it learned from (n of Eq. 7).
    pub fn learned_samples(&self) -> u64 {
        self.sfa.samples()
    }

    /// The source it is bound to, once it has learned from one.
    pub fn source(&self) -> Option<usize> {
        self.source
    }

    /// Consecutive learned samples with ε < δ so far.
    pub fn samples_below_delta(&self) -> u32 {
        self.below
    }

    /// Its slow-feature learner.
    pub fn sfa(&self) -> &SfaModule {
        &self.sfa
    }
}

/// A frozen module's running judgement of one source: its own ROC and error
/// window, fed with that source's samples (explain rule, ours).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct SourceTracker {
    roc: Roc,
    window: ErrorWindow,
}

/// A module frozen into the library: it no longer learns, but keeps judging
/// every source's samples.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrozenModule {
    sfa: SfaModule,
    source: usize,
    frozen_at: u64,
    /// Indexed by source; `None` until the module sees a sample of it.
    trackers: Vec<Option<SourceTracker>>,
}

impl FrozenModule {
    /// The source it learned.
    pub fn source(&self) -> usize {
        self.source
    }

    /// The channel's sample index (1-based count of observed samples) at
    /// which it froze.
    pub fn frozen_at(&self) -> u64 {
        self.frozen_at
    }

    /// Samples it learned from before freezing.
    pub fn learned_samples(&self) -> u64 {
        self.sfa.samples()
    }

    /// Its (frozen) slow-feature learner.
    pub fn sfa(&self) -> &SfaModule {
        &self.sfa
    }

    /// Mean of its error window on `source` (None if it has not seen it).
    pub fn window_mean(&self, source: usize) -> Option<f64> {
        self.tracker(source).map(|t| t.window.mean())
    }

    /// Samples of `source` it has judged (for its own source, counting the
    /// training samples).
    pub fn samples_of(&self, source: usize) -> u64 {
        self.tracker(source).map_or(0, |t| t.window.samples())
    }

    fn tracker(&self, source: usize) -> Option<&SourceTracker> {
        self.trackers.get(source).and_then(Option::as_ref)
    }

    /// Explain rule: at least `explain_min_samples` samples of the source
    /// with window mean below `explain_below`.
    fn explains(&self, source: usize, params: &ValidCuriosityParams) -> bool {
        self.tracker(source).is_some_and(|t| {
            t.window.samples() >= params.explain_min_samples
                && t.window.mean() < params.explain_below
        })
    }

    /// Feeds one sample of `source` to its ROC and window for that source.
    fn judge(&mut self, source: usize, x: &[f64], params: &ValidCuriosityParams) {
        if self.trackers.len() <= source {
            self.trackers.resize(source + 1, None);
        }
        let y = self.sfa.output(x);
        let tracker = self.trackers[source].get_or_insert_with(|| SourceTracker {
            roc: Roc::with_params(params),
            window: ErrorWindow::new(params.tau, params.initial_error),
        });
        let error = tracker.roc.update(y);
        tracker.window.push(error);
    }
}

/// What [`CuriosityChannel::observe`] did with one sample.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CuriosityStep {
    /// ξ_cur of Eq. 7; 0 unless the active module learned from the sample.
    pub xi_cur: f64,
    /// The active module learned from this sample.
    pub learned: bool,
    /// The library index of the module that froze on this sample, if any.
    pub frozen: Option<usize>,
    /// ε of the module that was active when the sample arrived (after the
    /// sample if it learned from it; the module may have frozen on it).
    pub epsilon: f64,
    /// Its slow feature y, if it learned from the sample.
    pub feature: Option<f64>,
    /// The library index of the first frozen module that explains this
    /// sample's source, if any (then the sample gave 0 and trained nothing).
    pub explained_by: Option<usize>,
    /// Some source has been seen, and every source seen so far is explained
    /// by a frozen module: ξ_cur is then identically zero for now (the
    /// agent's condition (3), §7).
    pub all_explained: bool,
}

/// The intMCA curiosity channel (§7): one active module learning, a library
/// of frozen ones, and the freeze, explain and bind rules (ours).
///
/// Module k's w₀ is drawn from ChaCha8(seed) on stream k, so the state
/// carries no RNG position and the channel is a pure function of its seed
/// and the samples it observed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CuriosityChannel {
    params: ValidCuriosityParams,
    m: usize,
    seed: u64,
    active: ActiveModule,
    /// Modules started so far (active included): the next w₀'s stream.
    started: u64,
    library: Vec<FrozenModule>,
    /// Sources seen so far, indexed by source.
    known: Vec<bool>,
    samples: u64,
}

pub(super) fn module_rng(seed: u64, k: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(k);
    rng
}

impl CuriosityChannel {
    /// Checks a signal dimension m: 1 ≤ m ≤ [`MAX_SIGNAL_DIM`] (what
    /// [`Self::new`] checks first, for callers that price a channel before
    /// they make it).
    pub fn check_signal_dim(m: usize) -> Result<()> {
        if m == 0 {
            return Err(bad("signal_dim", "must be at least 1"));
        }
        if m > MAX_SIGNAL_DIM {
            return Err(bad(
                "signal_dim",
                format!("{m} exceeds the limit of {MAX_SIGNAL_DIM}"),
            ));
        }
        Ok(())
    }

    /// A channel for m-dimensional signals (m ≥ 1) with a fresh active
    /// module and an empty library.
    pub fn new(m: usize, params: ValidCuriosityParams, seed: u64) -> Result<Self> {
        Self::check_signal_dim(m)?;
        let active = ActiveModule::fresh(m, &params, &mut module_rng(seed, 0));
        Ok(Self {
            params,
            m,
            seed,
            active,
            started: 1,
            library: Vec::new(),
            known: Vec::new(),
            samples: 0,
        })
    }

    fn validate(&self, source: usize, x: &[f64]) -> Result<()> {
        if source >= self.params.max_sources {
            return Err(bad(
                "source",
                format!(
                    "{source} is not below max_sources = {}",
                    self.params.max_sources
                ),
            ));
        }
        if x.len() != self.m {
            return Err(bad(
                "signal",
                format!("has {} components, expected {}", x.len(), self.m),
            ));
        }
        for (i, &v) in x.iter().enumerate() {
            if !v.is_finite() {
                return Err(AlgoError::NonFinite { field: "signal" });
            }
            if v.abs() > MAX_STIMULUS {
                return Err(bad(
                    "signal",
                    format!("component {i} = {v:e} exceeds the limit of ±{MAX_STIMULUS:e}"),
                ));
            }
        }
        Ok(())
    }

    /// One signal sample x from `source` (§7 "Freeze, explain, bind"):
    ///
    /// 1. every frozen module judges it with its ROC and window for `source`;
    /// 2. if some frozen module then explains `source` the sample gives
    ///    ξ_cur = 0 and trains nothing;
    /// 3. otherwise a fresh active module binds to `source`; the active
    ///    module learns from it only if bound to `source` (else ξ_cur = 0),
    ///    giving ξ_cur of Eq. 7;
    /// 4. once its ε < δ for `freeze_after` consecutive learned samples it is
    ///    frozen into the library, its training ROC and window becoming its
    ///    judgement of its own source (so that source is explained at once),
    ///    and a fresh module starts.
    pub fn observe(&mut self, source: usize, x: &[f64]) -> Result<CuriosityStep> {
        self.validate(source, x)?;
        self.samples += 1;
        if self.known.len() <= source {
            self.known.resize(source + 1, false);
        }
        self.known[source] = true;
        let params = &self.params;
        for module in &mut self.library {
            module.judge(source, x, params);
        }
        let explained_by = self.explained_by(source);
        let mut step = CuriosityStep {
            xi_cur: 0.0,
            learned: false,
            frozen: None,
            epsilon: self.active.estimation_error(),
            feature: None,
            explained_by,
            all_explained: false,
        };
        let bound_here = self.active.source.is_none_or(|s| s == source);
        if explained_by.is_none() && bound_here {
            self.active.source = Some(source);
            let learned = self.active.learn(x, &self.params);
            step.xi_cur = learned.xi;
            step.learned = true;
            step.epsilon = learned.epsilon;
            step.feature = Some(learned.y);
            if self.active.below >= self.params.freeze_after && self.library.len() < MAX_LIBRARY {
                step.frozen = Some(self.freeze(source));
            }
        }
        step.all_explained = self.all_explained();
        Ok(step)
    }

    /// Moves the active module into the library and starts a fresh one.
    fn freeze(&mut self, source: usize) -> usize {
        let fresh = ActiveModule::fresh(
            self.m,
            &self.params,
            &mut module_rng(self.seed, self.started),
        );
        self.started += 1;
        let done = std::mem::replace(&mut self.active, fresh);
        let mut trackers = vec![None; source + 1];
        trackers[source] = Some(SourceTracker {
            roc: done.roc,
            window: done.progress.window,
        });
        self.library.push(FrozenModule {
            sfa: done.sfa,
            source,
            frozen_at: self.samples,
            trackers,
        });
        self.library.len() - 1
    }

    /// The first frozen module that explains `source`, if any.
    pub fn explained_by(&self, source: usize) -> Option<usize> {
        self.library
            .iter()
            .position(|module| module.explains(source, &self.params))
    }

    /// Some source has been seen and every source seen is explained (ξ_cur
    /// is then identically zero until a source becomes unexplained again).
    /// False before any sample: nothing is explained yet.
    pub fn all_explained(&self) -> bool {
        let mut seen = self
            .known
            .iter()
            .enumerate()
            .filter(|&(_, &k)| k)
            .peekable();
        seen.peek().is_some() && seen.all(|(s, _)| self.explained_by(s).is_some())
    }

    /// Sources seen so far.
    pub fn known_sources(&self) -> impl Iterator<Item = usize> + '_ {
        self.known
            .iter()
            .enumerate()
            .filter_map(|(s, &k)| k.then_some(s))
    }

    /// The module currently learning.
    pub fn active(&self) -> &ActiveModule {
        &self.active
    }

    /// ε of the active module.
    pub fn epsilon(&self) -> f64 {
        self.active.estimation_error()
    }

    /// The frozen modules, in the order they froze.
    pub fn library(&self) -> &[FrozenModule] {
        &self.library
    }

    /// Number of frozen modules (signal sources learned).
    pub fn module_count(&self) -> usize {
        self.library.len()
    }

    /// Samples observed so far (all sources).
    pub fn samples(&self) -> u64 {
        self.samples
    }

    /// Signal dimension m.
    pub fn signal_dim(&self) -> usize {
        self.m
    }

    /// The seed of the modules' w₀.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// The parameters.
    pub fn params(&self) -> &ValidCuriosityParams {
        &self.params
    }
}
