//! What one parameter is: its name, its kind (with the range it may take),
//! its default, its unit and a one-line doc. The tables of
//! [`super::table`] are made of these, and everything that describes a
//! parameter (the core's validation, the server's OpenAPI schema, the
//! docs' tables, the Python client's options) reads them from there.

use super::super::error::{AlgoError, Result};

/// One end of a real parameter's range.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Bound {
    /// The value may equal it.
    Incl(f64),
    /// The value must lie strictly beyond it.
    Excl(f64),
    /// No bound on this side, beyond being finite.
    None,
}

/// The largest value of an integer parameter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Max {
    /// A fixed bound.
    Value(u64),
    /// A server limit: the command-line flag that sets it, and the hard
    /// bound the core itself enforces (the flag cannot raise it beyond).
    Limit {
        /// The `mcapi serve` flag, e.g. `--max-history`.
        flag: &'static str,
        /// The core's own bound.
        hard: u64,
    },
}

impl Max {
    /// The core's own bound.
    pub fn hard(self) -> u64 {
        match self {
            Self::Value(v) | Self::Limit { hard: v, .. } => v,
        }
    }
}

/// What a parameter holds, with the range it may take.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Kind {
    /// A finite real number between `lower` and `upper`.
    Real {
        /// Lower end.
        lower: Bound,
        /// Upper end.
        upper: Bound,
    },
    /// An unsigned integer in `min..=max`.
    Integer {
        /// Smallest value.
        min: u64,
        /// Largest value.
        max: Max,
    },
    /// One real per stimulus dimension, each between `lower` and `upper`.
    PerStimulus {
        /// Lower end of each entry.
        lower: Bound,
        /// Upper end of each entry.
        upper: Bound,
    },
    /// A constant real between `lower` and `upper`, or one of `names`.
    RealOrName {
        /// Lower end of the constant.
        lower: Bound,
        /// Upper end of the constant.
        upper: Bound,
        /// The named rules.
        names: &'static [&'static str],
    },
    /// One of these names.
    Choice(&'static [&'static str]),
    /// An object of its own schema (named).
    Object(&'static str),
}

/// A parameter's default.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Default {
    /// This real.
    Real(f64),
    /// This integer.
    Integer(u64),
    /// This name.
    Name(&'static str),
    /// Every entry 1.
    AllOnes,
    /// Drawn at random by the server, and returned.
    Drawn,
    /// Left out: the feature is off.
    Absent,
}

/// One parameter, declared once.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Param {
    /// Its name, in JSON, in the proto and in the Python client.
    pub name: &'static str,
    /// What it holds and the range it may take.
    pub kind: Kind,
    /// Its value when the client leaves it out.
    pub default: Default,
    /// Its unit, empty when it has none.
    pub unit: &'static str,
    /// One line saying what it is (symbols as the paper writes them).
    pub doc: &'static str,
    /// The section of docs/algorithm.md that explains it, as a link
    /// target relative to `docs/` (empty when none).
    pub see: &'static str,
}

impl Param {
    /// The value of a real parameter: `value`, or the default when absent,
    /// checked to be finite and within the range.
    pub fn real(&self, value: Option<f64>) -> Result<f64> {
        let x = match (value, self.default) {
            (Some(x), _) => x,
            (None, Default::Real(d)) => d,
            (None, _) => return Err(self.bad("is required")),
        };
        let (lower, upper) = match self.kind {
            Kind::Real { lower, upper } | Kind::RealOrName { lower, upper, .. } => (lower, upper),
            _ => return Err(self.bad("is not a real parameter")),
        };
        self.within(x, lower, upper, None)
    }

    /// The value of an integer parameter: `value`, or the default when
    /// absent, checked to lie in `min..=max` (the core's bound).
    pub fn integer(&self, value: Option<u64>) -> Result<u64> {
        let n = match (value, self.default) {
            (Some(n), _) => n,
            (None, Default::Integer(d)) => d,
            (None, _) => return Err(self.bad("is required")),
        };
        let Kind::Integer { min, max } = self.kind else {
            return Err(self.bad("is not an integer parameter"));
        };
        if n < min || n > max.hard() {
            return Err(self.bad(format!("{n} is not in {min}..={}", max.hard())));
        }
        Ok(n)
    }

    /// One entry per stimulus dimension, each within the range; all ones
    /// when absent.
    pub fn per_stimulus(&self, value: Option<&[f64]>, n_stimuli: usize) -> Result<Vec<f64>> {
        let Kind::PerStimulus { lower, upper } = self.kind else {
            return Err(self.bad("is not a per-stimulus parameter"));
        };
        let Some(v) = value else {
            return Ok(vec![1.0; n_stimuli]);
        };
        if v.len() != n_stimuli {
            return Err(self.bad(format!(
                "has {} entries, expected one per stimulus ({n_stimuli})",
                v.len()
            )));
        }
        for (i, &x) in v.iter().enumerate() {
            self.within(x, lower, upper, Some(i))?;
        }
        Ok(v.to_vec())
    }

    fn within(&self, x: f64, lower: Bound, upper: Bound, entry: Option<usize>) -> Result<f64> {
        let what = match entry {
            Some(i) => format!("entry {i} = {x}"),
            None => format!("{x}"),
        };
        if !x.is_finite() {
            return Err(self.bad(match entry {
                Some(_) => format!("{what} is not in {}", range(lower, upper)),
                None => "must be a finite number".to_owned(),
            }));
        }
        let above = match lower {
            Bound::Incl(a) => x >= a,
            Bound::Excl(a) => x > a,
            Bound::None => true,
        };
        let below = match upper {
            Bound::Incl(b) => x <= b,
            Bound::Excl(b) => x < b,
            Bound::None => true,
        };
        if above && below {
            Ok(x)
        } else {
            Err(self.bad(format!("{what} is not in {}", range(lower, upper))))
        }
    }

    /// A valid value, as JSON: the default where there is one, one entry
    /// for a per-stimulus parameter, `null` for an absent object.
    pub fn example(&self) -> serde_json::Value {
        match self.default {
            Default::Real(x) => x.into(),
            Default::Integer(n) => n.into(),
            Default::Name(name) => name.into(),
            Default::AllOnes => vec![1.0].into(),
            Default::Drawn => 7.into(),
            Default::Absent => serde_json::Value::Null,
        }
    }

    /// The name of the parameter's value type, its name in PascalCase
    /// (`stimulus_rate` → `StimulusRate`), as the OpenAPI document, the
    /// proto and the Python client name a type of its own.
    pub fn type_name(&self) -> String {
        self.name
            .split('_')
            .map(|w| {
                let mut c = w.chars();
                c.next()
                    .map(|f| f.to_uppercase().chain(c).collect::<String>())
                    .unwrap_or_default()
            })
            .collect()
    }

    /// The error naming this parameter.
    pub fn bad(&self, reason: impl Into<String>) -> AlgoError {
        AlgoError::InvalidParameter {
            name: self.name,
            reason: reason.into(),
        }
    }

    /// The range in words, as the docs and the error messages write it:
    /// `(0, 0.5]`, `[0, inf)`, `1..=100000`, `"lockstep" or "async"`.
    pub fn allowed(&self) -> String {
        match self.kind {
            Kind::Real { lower, upper } | Kind::PerStimulus { lower, upper } => range(lower, upper),
            Kind::Integer { min, max } => match max {
                Max::Value(u64::MAX) => format!("{min} or more"),
                Max::Value(v) => format!("{min}..={v}"),
                Max::Limit { flag, .. } => format!("{min} to `{flag}`"),
            },
            Kind::RealOrName {
                lower,
                upper,
                names,
            } => {
                let names: Vec<String> = names.iter().map(|n| format!("\"{n}\"")).collect();
                format!(
                    "{} or a number in {}",
                    names.join(", "),
                    range(lower, upper)
                )
            }
            Kind::Choice(names) => {
                let names: Vec<String> = names.iter().map(|n| format!("\"{n}\"")).collect();
                names.join(" or ")
            }
            Kind::Object(schema) => format!("a `{schema}` object"),
        }
    }

    /// The default in words: `0.01`, `all 1`, `"sample_mean"`, `drawn by
    /// the server`, `none`.
    pub fn default_text(&self) -> String {
        match self.default {
            Default::Real(x) => num(x),
            Default::Integer(n) => n.to_string(),
            Default::Name(name) => format!("\"{name}\""),
            Default::AllOnes => "all 1".to_owned(),
            Default::Drawn => "drawn by the server".to_owned(),
            Default::Absent => "none".to_owned(),
        }
    }
}

/// `(a, b]`-style interval notation, with `-inf`/`inf` for a missing end.
pub fn range(lower: Bound, upper: Bound) -> String {
    let (open, a) = match lower {
        Bound::Incl(a) => ('[', num(a)),
        Bound::Excl(a) => ('(', num(a)),
        Bound::None => ('(', "-inf".to_owned()),
    };
    let (close, b) = match upper {
        Bound::Incl(b) => (']', num(b)),
        Bound::Excl(b) => (')', num(b)),
        Bound::None => (')', "inf".to_owned()),
    };
    format!("{open}{a}, {b}{close}")
}

/// A number as the docs write it: `0.5`, `1`, `800`, `1e-6`.
pub fn num(x: f64) -> String {
    if x != 0.0 && (x.abs() < 1e-3 || x.abs() >= 1e6) {
        format!("{x:e}")
    } else {
        format!("{x}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const P: Param = Param {
        name: "p",
        kind: Kind::Real {
            lower: Bound::Excl(0.0),
            upper: Bound::Incl(0.5),
        },
        default: Default::Real(0.01),
        unit: "",
        doc: "a test parameter",
        see: "",
    };

    #[test]
    fn real_takes_the_default_and_refuses_what_is_out_of_range() {
        assert_eq!(P.real(None).expect("default"), 0.01);
        assert_eq!(P.real(Some(0.5)).expect("upper end included"), 0.5);
        for bad in [0.0, -1.0, 0.50001, f64::NAN, f64::INFINITY] {
            let msg = P.real(Some(bad)).expect_err("refused").to_string();
            assert!(msg.contains("`p`"), "{msg}");
        }
        assert!(
            P.real(Some(0.0))
                .expect_err("lower end excluded")
                .to_string()
                .contains("0 is not in (0, 0.5]")
        );
    }

    #[test]
    fn ranges_and_defaults_read_as_the_docs_write_them() {
        assert_eq!(range(Bound::Incl(0.0), Bound::None), "[0, inf)");
        assert_eq!(range(Bound::Excl(0.0), Bound::Excl(1.0)), "(0, 1)");
        assert_eq!(num(1e-8), "1e-8");
        assert_eq!(P.default_text(), "0.01");
        let rate = Param {
            name: "stimulus_rate",
            ..P
        };
        assert_eq!(rate.type_name(), "StimulusRate");
    }
}
