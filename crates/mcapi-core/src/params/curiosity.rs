//! The curiosity channel's constants checked against their table
//! ([`CURIOSITY_PARAMS`]): the check lives with the tables, so the channel
//! (`crate::curiosity`) needs nothing of them.

use super::CURIOSITY_PARAMS;
use crate::curiosity::{CuriosityParams, ValidCuriosityParams};
use crate::error::Result;

/// A constant's value, as [`CuriosityParams::check`] hands it to its
/// entry of [`CURIOSITY_PARAMS`].
#[derive(Debug, Clone, Copy, PartialEq)]
enum Value {
    Real(f64),
    Integer(u64),
}

impl CuriosityParams {
    /// The constants in the order of [`CURIOSITY_PARAMS`].
    fn values(&self) -> [Value; CURIOSITY_PARAMS.len()] {
        let Self {
            max_centres,
            beta,
            tau,
            lag,
            eta_c,
            gain,
            clip,
            delta,
            freeze_after,
            explain_below,
            explain_min_samples,
            dt,
            floor_rel,
            floor_abs,
            initial_error,
            max_sources,
        } = self;
        let int = |n: usize| Value::Integer(u64::try_from(n).unwrap_or(u64::MAX));
        [
            int(*max_centres),
            Value::Real(*beta),
            int(*tau),
            int(*lag),
            Value::Real(*eta_c),
            Value::Real(*gain),
            Value::Real(*clip),
            Value::Real(*delta),
            Value::Integer(u64::from(*freeze_after)),
            Value::Real(*explain_below),
            Value::Integer(*explain_min_samples),
            Value::Real(*dt),
            Value::Real(*floor_rel),
            Value::Real(*floor_abs),
            Value::Real(*initial_error),
            int(*max_sources),
        ]
    }

    /// Validates every field once, against its entry of
    /// [`CURIOSITY_PARAMS`] (range, and the core's hard bound of a limit).
    pub fn check(&self) -> Result<ValidCuriosityParams> {
        for (param, value) in CURIOSITY_PARAMS.iter().zip(self.values()) {
            match value {
                Value::Real(x) => {
                    param.real(Some(x))?;
                }
                Value::Integer(n) => {
                    param.integer(Some(n))?;
                }
            }
        }
        Ok(ValidCuriosityParams::checked(self.clone()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::curiosity::MAX_WINDOW;
    use crate::params::spec::Default as TableDefault;

    /// The struct, its serde names, its [`Default`] and the table agree.
    #[test]
    fn the_table_declares_every_constant_with_its_default() {
        let json = serde_json::to_value(CuriosityParams::default()).expect("serialises");
        let object = json.as_object().expect("an object");
        assert_eq!(object.len(), CURIOSITY_PARAMS.len());
        let values = CuriosityParams::default().values();
        for (param, value) in CURIOSITY_PARAMS.iter().zip(values) {
            assert!(
                object.contains_key(param.name),
                "{} is not a field",
                param.name
            );
            match (param.default, value) {
                (TableDefault::Real(d), Value::Real(x)) => assert_eq!(d, x, "{}", param.name),
                (TableDefault::Integer(d), Value::Integer(n)) => {
                    assert_eq!(d, n, "{}", param.name);
                }
                other => panic!(
                    "{}: the table's default and the field differ: {other:?}",
                    param.name
                ),
            }
        }
        CuriosityParams::default()
            .check()
            .expect("the defaults are valid");
    }

    #[test]
    fn each_constant_is_checked_against_its_range() {
        let cases = [
            (
                CuriosityParams {
                    max_centres: 1,
                    ..Default::default()
                },
                "`max_centres`",
            ),
            (
                CuriosityParams {
                    beta: 0.0,
                    ..Default::default()
                },
                "`beta`",
            ),
            (
                CuriosityParams {
                    tau: MAX_WINDOW + 1,
                    ..Default::default()
                },
                "`tau`",
            ),
            (
                CuriosityParams {
                    eta_c: 1.0,
                    ..Default::default()
                },
                "`eta_c`",
            ),
            (
                CuriosityParams {
                    gain: f64::INFINITY,
                    ..Default::default()
                },
                "`gain`",
            ),
            (
                CuriosityParams {
                    gain: 1e308,
                    ..Default::default()
                },
                "`gain`",
            ),
            (
                CuriosityParams {
                    clip: 1e308,
                    ..Default::default()
                },
                "`clip`",
            ),
            (
                CuriosityParams {
                    freeze_after: 0,
                    ..Default::default()
                },
                "`freeze_after`",
            ),
            (
                CuriosityParams {
                    floor_rel: 1.0,
                    ..Default::default()
                },
                "`floor_rel`",
            ),
            (
                CuriosityParams {
                    initial_error: -1.0,
                    ..Default::default()
                },
                "`initial_error`",
            ),
            (
                CuriosityParams {
                    max_sources: 0,
                    ..Default::default()
                },
                "`max_sources`",
            ),
        ];
        for (params, name) in cases {
            let msg = params.check().expect_err("refused").to_string();
            assert!(msg.contains(name), "{msg:?} should name {name}");
        }
    }
}
