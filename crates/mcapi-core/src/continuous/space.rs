//! The observation space of a continuous world: a box [low, high]^d, and
//! what the agent does with an observation outside it (docs/algorithm.md
//! §9.1).
//!
//! Every basis works on the normalised point s = (x − low) / (high − low)
//! ∈ [0, 1]^d, so the box is the only place that knows the client's units.

use serde::{Deserialize, Serialize};

use crate::error::{AlgoError, Result};

/// Largest dimension d of an observation space.
pub const MAX_DIM: usize = 64;

/// Largest |low| or |high| of a coordinate, so that high − low is finite
/// and normalising loses no more than a few bits.
pub const MAX_COORDINATE: f64 = 1e12;

/// What an observation outside the box does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OutOfBounds {
    /// Clip each coordinate into [low, high] and count the observation.
    #[default]
    Clip,
    /// Refuse the observation.
    Refuse,
}

/// A box [low, high]^d, as a client sends it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObservationSpace {
    /// Lower corner, one coordinate per dimension.
    pub low: Vec<f64>,
    /// Upper corner; each coordinate strictly above its `low`.
    pub high: Vec<f64>,
}

/// Where an observation fell.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Placement {
    /// Inside the box.
    Inside,
    /// Outside, clipped into it.
    Clipped,
}

impl ObservationSpace {
    /// Checks the box: 1 ≤ d ≤ [`MAX_DIM`], finite corners within
    /// ±[`MAX_COORDINATE`], low < high in every dimension.
    pub fn check(&self) -> Result<()> {
        let d = self.low.len();
        if d == 0 || d > MAX_DIM {
            return Err(bad(format!(
                "`low` has {d} coordinates; a space has 1..={MAX_DIM} dimensions"
            )));
        }
        if self.high.len() != d {
            return Err(bad(format!(
                "`high` has {} coordinates but `low` has {d}",
                self.high.len()
            )));
        }
        for (j, (&lo, &hi)) in self.low.iter().zip(&self.high).enumerate() {
            if !lo.is_finite()
                || !hi.is_finite()
                || lo.abs() > MAX_COORDINATE
                || hi.abs() > MAX_COORDINATE
            {
                return Err(bad(format!(
                    "dimension {j}: low and high must be finite numbers within ±{MAX_COORDINATE:e}"
                )));
            }
            if lo >= hi {
                return Err(bad(format!(
                    "dimension {j}: low {lo} is not below high {hi}"
                )));
            }
        }
        Ok(())
    }

    /// The dimension d.
    pub fn dim(&self) -> usize {
        self.low.len()
    }

    /// Normalises `x` into `s` ∈ [0, 1]^d. A wrong dimension or a
    /// non-finite coordinate is an error; a coordinate outside the box is
    /// clipped or refused as `rule` says.
    pub fn normalise_into(
        &self,
        x: &[f64],
        rule: OutOfBounds,
        s: &mut Vec<f64>,
    ) -> Result<Placement> {
        let d = self.dim();
        if x.len() != d {
            return Err(AlgoError::InvalidObservation(format!(
                "`observation` has {} coordinates; the observation space has {d}",
                x.len()
            )));
        }
        if let Some(j) = x.iter().position(|v| !v.is_finite()) {
            return Err(AlgoError::InvalidObservation(format!(
                "`observation` coordinate {j} is not a finite number"
            )));
        }
        let mut placement = Placement::Inside;
        s.clear();
        for (j, ((&v, &lo), &hi)) in x.iter().zip(&self.low).zip(&self.high).enumerate() {
            if v < lo || v > hi {
                if rule == OutOfBounds::Refuse {
                    return Err(AlgoError::InvalidObservation(format!(
                        "`observation` coordinate {j} = {v} is outside [{lo}, {hi}] \
                         (the session refuses observations outside its space)"
                    )));
                }
                placement = Placement::Clipped;
            }
            s.push(((v.clamp(lo, hi) - lo) / (hi - lo)).clamp(0.0, 1.0));
        }
        Ok(placement)
    }

    /// The point of the box at normalised `s` (the inverse of
    /// [`Self::normalise_into`] inside the box).
    pub fn denormalise(&self, s: &[f64]) -> Vec<f64> {
        s.iter()
            .zip(&self.low)
            .zip(&self.high)
            .map(|((s, lo), hi)| lo + s * (hi - lo))
            .collect()
    }
}

fn bad(msg: String) -> AlgoError {
    AlgoError::InvalidModel(format!("observation_space: {msg}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(d: usize) -> ObservationSpace {
        ObservationSpace {
            low: vec![0.0; d],
            high: vec![1.0; d],
        }
    }

    #[test]
    fn bounds_of_the_box_are_checked() {
        assert!(unit(2).check().is_ok());
        assert!(unit(0).check().is_err());
        assert!(unit(MAX_DIM + 1).check().is_err());
        let inverted = ObservationSpace {
            low: vec![1.0],
            high: vec![0.0],
        };
        assert!(inverted.check().is_err());
        let flat = ObservationSpace {
            low: vec![1.0],
            high: vec![1.0],
        };
        assert!(flat.check().is_err());
        let nan = ObservationSpace {
            low: vec![f64::NAN],
            high: vec![1.0],
        };
        assert!(nan.check().is_err());
        let huge = ObservationSpace {
            low: vec![-1e300],
            high: vec![1e300],
        };
        assert!(huge.check().is_err());
        let ragged = ObservationSpace {
            low: vec![0.0, 0.0],
            high: vec![1.0],
        };
        assert!(ragged.check().is_err());
    }

    #[test]
    fn normalising_clips_or_refuses_and_rejects_nan() {
        let space = ObservationSpace {
            low: vec![-1.0, 0.0],
            high: vec![1.0, 10.0],
        };
        let mut s = Vec::new();
        assert_eq!(
            space
                .normalise_into(&[0.0, 5.0], OutOfBounds::Clip, &mut s)
                .ok(),
            Some(Placement::Inside)
        );
        assert_eq!(s, vec![0.5, 0.5]);
        assert_eq!(
            space
                .normalise_into(&[2.0, -3.0], OutOfBounds::Clip, &mut s)
                .ok(),
            Some(Placement::Clipped)
        );
        assert_eq!(s, vec![1.0, 0.0]);
        assert!(
            space
                .normalise_into(&[2.0, 1.0], OutOfBounds::Refuse, &mut s)
                .is_err()
        );
        assert!(
            space
                .normalise_into(&[f64::NAN, 1.0], OutOfBounds::Clip, &mut s)
                .is_err()
        );
        assert!(
            space
                .normalise_into(&[f64::INFINITY, 1.0], OutOfBounds::Clip, &mut s)
                .is_err()
        );
        assert!(
            space
                .normalise_into(&[0.0], OutOfBounds::Clip, &mut s)
                .is_err()
        );
        assert_eq!(space.denormalise(&[0.5, 0.5]), vec![0.0, 5.0]);
    }
}
