//! The body of `POST /v1/sessions/{id}/observations`, the hottest request:
//! one observation (`{"state": 3, "stimulus": [1, 0]}`) or a batch
//! (`{"observations": [...]}`).
//!
//! Two readers that must agree. The **fast** one types the bytes in one
//! pass (keys borrowed from the body, no `serde_json::Value` tree): it
//! takes only the plain form, a JSON object of known keys, each at most
//! once, with `Content-Type: application/json`. Anything else (a syntax
//! error, an array where an object belongs, a duplicate or escaped key, an
//! unusual content type) goes to the **slow** one, the general path every
//! other body takes ([`JsonValue`], [`require_objects`], then serde), which
//! decides and words the error. So a client's mistake gets exactly the
//! message it got before the fast reader existed, and a body the slow
//! reader accepts gives the same observations from either reader: numbers
//! are read as JSON Schema reads them (`3.0` is the index 3, see
//! [`integral_numbers_as_integers`](crate::api::extract::integral_numbers_as_integers)),
//! and a stimulus or signal component `-0.0` becomes `0.0`, as the slow
//! reader's rewrite makes it. The unit tests below check the agreement on
//! generated bodies.

use std::fmt;

use axum::body::Bytes;
use axum::extract::{FromRequest, Request};
use axum::http::{HeaderMap, header};
use serde::Deserialize;
use serde::de::{self, DeserializeSeed, Deserializer, MapAccess, SeqAccess, Visitor};
use serde_json::Value;

use crate::api::error::ApiError;
use crate::api::extract::{
    JsonValue, OBSERVE_OBJECTS, integral_numbers_as_integers, require_objects,
};
use crate::service::{ObservationIn, ServiceError};
use mcapi_core::spec::ActionRef;

/// An observation body: one observation or a batch.
#[derive(Debug, Clone, PartialEq)]
pub enum ObserveBody {
    /// `{"state": ..., ...}`.
    One(ObservationIn),
    /// `{"observations": [...]}`.
    Batch(Vec<ObservationIn>),
}

impl<S> FromRequest<S> for ObserveBody
where
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, ApiError> {
        if !plain_json(req.headers()) {
            let JsonValue(value) = JsonValue::from_request(req, state).await?;
            return Ok(slow_from_value(value)?);
        }
        // The server's body limit applies (`DefaultBodyLimit`), as for `Json`.
        let bytes = Bytes::from_request(req, state).await.map_err(|rejection| {
            ApiError(
                if rejection.status() == axum::http::StatusCode::PAYLOAD_TOO_LARGE {
                    ServiceError::PayloadTooLarge(
                        "the request body is larger than the server accepts".into(),
                    )
                } else {
                    ServiceError::BadRequest(format!(
                        "malformed JSON body: {}",
                        rejection.body_text()
                    ))
                },
            )
        })?;
        Ok(parse(&bytes)?)
    }
}

/// `Content-Type: application/json` exactly (any letter case), the form
/// clients send; other JSON types (`; charset=utf-8`, `+json`) and wrong
/// ones take the general path, which checks them.
fn plain_json(headers: &HeaderMap) -> bool {
    headers
        .get(header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().eq_ignore_ascii_case(b"application/json"))
}

/// The observations of a JSON body: the fast reader, or the slow one for
/// anything it does not take.
pub fn parse(bytes: &[u8]) -> Result<ObserveBody, ServiceError> {
    match fast(bytes) {
        Some(body) => Ok(body),
        None => slow(bytes),
    }
}

/// The fast reader: `None` for anything but the plain form.
pub fn fast(bytes: &[u8]) -> Option<ObserveBody> {
    let mut de = serde_json::Deserializer::from_slice(bytes);
    let body = de.deserialize_map(BodyVisitor).ok()?;
    de.end().ok()?;
    Some(body)
}

/// The slow reader: the general JSON path with its exact messages.
pub fn slow(bytes: &[u8]) -> Result<ObserveBody, ServiceError> {
    let axum::Json(mut value) = axum::Json::<Value>::from_bytes(bytes).map_err(|rejection| {
        ServiceError::BadRequest(format!("malformed JSON body: {}", rejection.body_text()))
    })?;
    integral_numbers_as_integers(&mut value);
    slow_from_value(value)
}

/// A batch, replayed in order.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ObserveBatch {
    observations: Vec<ObservationIn>,
}

fn slow_from_value(value: Value) -> Result<ObserveBody, ServiceError> {
    require_objects(&value, OBSERVE_OBJECTS)?;
    let parse_err =
        |e: serde_json::Error| ServiceError::BadRequest(format!("malformed observation: {e}"));
    if value.get("observations").is_some() {
        let ObserveBatch { observations } = serde_json::from_value(value).map_err(parse_err)?;
        Ok(ObserveBody::Batch(observations))
    } else {
        Ok(ObserveBody::One(
            serde_json::from_value(value).map_err(parse_err)?,
        ))
    }
}

/// Any error: the fast reader only says "not mine".
fn no<E: de::Error>() -> E {
    E::custom("not the plain form")
}

/// The fields of one observation as they arrive, each at most once.
#[derive(Default)]
struct Fields {
    state: Option<Option<usize>>,
    observation: Option<Option<Vec<f64>>>,
    stimulus: Option<Option<Vec<f64>>>,
    action_taken: Option<Option<ActionRef>>,
    signal: Option<Option<Vec<f64>>>,
    signal_source: Option<Option<usize>>,
    seq: Option<Option<u64>>,
}

impl Fields {
    fn is_empty(&self) -> bool {
        self.state.is_none()
            && self.observation.is_none()
            && self.stimulus.is_none()
            && self.action_taken.is_none()
            && self.signal.is_none()
            && self.signal_source.is_none()
            && self.seq.is_none()
    }

    /// Reads the value of `key`; false for a key that is not a field.
    fn read<'de, A: MapAccess<'de>>(&mut self, key: &str, map: &mut A) -> Result<bool, A::Error> {
        fn once<T, E: de::Error>(slot: &mut Option<T>, value: T) -> Result<(), E> {
            match slot {
                Some(_) => Err(no()),
                None => {
                    *slot = Some(value);
                    Ok(())
                }
            }
        }
        match key {
            "state" => once(&mut self.state, map.next_value_seed(Nullable(Index))?)?,
            "observation" => once(
                &mut self.observation,
                map.next_value_seed(Nullable(Numbers))?,
            )?,
            "stimulus" => once(&mut self.stimulus, map.next_value_seed(Nullable(Numbers))?)?,
            "action_taken" => once(
                &mut self.action_taken,
                map.next_value_seed(Nullable(Action))?,
            )?,
            "signal" => once(&mut self.signal, map.next_value_seed(Nullable(Numbers))?)?,
            "signal_source" => {
                once(
                    &mut self.signal_source,
                    map.next_value_seed(Nullable(Index))?,
                )?;
            }
            "seq" => once(&mut self.seq, map.next_value_seed(Nullable(Seq))?)?,
            _ => return Ok(false),
        }
        Ok(true)
    }

    fn finish<E: de::Error>(self) -> Result<ObservationIn, E> {
        Ok(ObservationIn {
            state: self.state.flatten(),
            observation: self.observation.flatten(),
            stimulus: self.stimulus.flatten(),
            action_taken: self.action_taken.flatten(),
            signal: self.signal.flatten(),
            signal_source: self.signal_source.flatten(),
            seq: self.seq.flatten(),
        })
    }
}

/// The top-level object.
struct BodyVisitor;

impl<'de> Visitor<'de> for BodyVisitor {
    type Value = ObserveBody;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("an observation object")
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<ObserveBody, A::Error> {
        let mut fields = Fields::default();
        let mut batch: Option<Vec<ObservationIn>> = None;
        while let Some(key) = map.next_key::<&'de str>()? {
            if key == "observations" {
                if batch.is_some() {
                    return Err(no());
                }
                batch = Some(map.next_value_seed(Items)?);
            } else if !fields.read(key, &mut map)? {
                return Err(no());
            }
        }
        match batch {
            None => Ok(ObserveBody::One(fields.finish()?)),
            Some(items) if fields.is_empty() => Ok(ObserveBody::Batch(items)),
            Some(_) => Err(no()),
        }
    }
}

/// One observation of a batch: an object, never an array of its fields.
struct ItemVisitor;

impl<'de> Visitor<'de> for ItemVisitor {
    type Value = ObservationIn;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("an observation object")
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<ObservationIn, A::Error> {
        let mut fields = Fields::default();
        while let Some(key) = map.next_key::<&'de str>()? {
            if !fields.read(key, &mut map)? {
                return Err(no());
            }
        }
        fields.finish()
    }
}

/// The `observations` array.
struct Items;

impl<'de> DeserializeSeed<'de> for Items {
    type Value = Vec<ObservationIn>;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
        d.deserialize_seq(self)
    }
}

impl<'de> Visitor<'de> for Items {
    type Value = Vec<ObservationIn>;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("an array of observations")
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
        // The body limit bounds the array; no size hint is trusted.
        let mut items = Vec::new();
        while let Some(item) = seq.next_element_seed(Item)? {
            items.push(item);
        }
        Ok(items)
    }
}

struct Item;

impl<'de> DeserializeSeed<'de> for Item {
    type Value = ObservationIn;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
        d.deserialize_map(ItemVisitor)
    }
}

/// `null` as `None`, anything else by the inner seed.
struct Nullable<T>(T);

impl<'de, T: DeserializeSeed<'de>> DeserializeSeed<'de> for Nullable<T> {
    type Value = Option<T::Value>;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
        d.deserialize_option(self)
    }
}

impl<'de, T: DeserializeSeed<'de>> Visitor<'de> for Nullable<T> {
    type Value = Option<T::Value>;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("a value or null")
    }

    fn visit_none<E: de::Error>(self) -> Result<Self::Value, E> {
        Ok(None)
    }

    fn visit_unit<E: de::Error>(self) -> Result<Self::Value, E> {
        Ok(None)
    }

    fn visit_some<D: Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
        self.0.deserialize(d).map(Some)
    }
}

/// A non-negative integer, also written as a float with no fractional part
/// (`3.0`, `1e3`) below 2^64, as the slow reader's rewrite reads it.
struct Index;

impl<'de> DeserializeSeed<'de> for Index {
    type Value = usize;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<usize, D::Error> {
        d.deserialize_any(self)
    }
}

impl Visitor<'_> for Index {
    type Value = usize;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("a non-negative integer")
    }

    fn visit_u64<E: de::Error>(self, v: u64) -> Result<usize, E> {
        usize::try_from(v).map_err(|_| no())
    }

    fn visit_f64<E: de::Error>(self, v: f64) -> Result<usize, E> {
        // 2^64, exact in f64.
        const TWO_64: f64 = 18_446_744_073_709_551_616.0;
        if v.fract() == 0.0 && (0.0..TWO_64).contains(&v) {
            usize::try_from(v as u64).map_err(|_| no())
        } else {
            Err(no())
        }
    }
}

/// A `seq`: an integer below 2^64, also written as a float with no
/// fractional part, as the slow reader's rewrite reads it; anything else
/// goes to the slow reader, whose message names the field and the range.
struct Seq;

impl<'de> DeserializeSeed<'de> for Seq {
    type Value = u64;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<u64, D::Error> {
        d.deserialize_any(self)
    }
}

impl Visitor<'_> for Seq {
    type Value = u64;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("a non-negative integer")
    }

    fn visit_u64<E: de::Error>(self, v: u64) -> Result<u64, E> {
        Ok(v)
    }

    fn visit_f64<E: de::Error>(self, v: f64) -> Result<u64, E> {
        // 2^64, exact in f64.
        const TWO_64: f64 = 18_446_744_073_709_551_616.0;
        if v.fract() == 0.0 && (0.0..TWO_64).contains(&v) {
            Ok(v as u64)
        } else {
            Err(no())
        }
    }
}

/// An action by index (as [`Index`] reads it) or by name.
struct Action;

impl<'de> DeserializeSeed<'de> for Action {
    type Value = ActionRef;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<ActionRef, D::Error> {
        d.deserialize_any(self)
    }
}

impl Visitor<'_> for Action {
    type Value = ActionRef;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("an action index or name")
    }

    fn visit_u64<E: de::Error>(self, v: u64) -> Result<ActionRef, E> {
        Index.visit_u64(v).map(ActionRef::Index)
    }

    fn visit_f64<E: de::Error>(self, v: f64) -> Result<ActionRef, E> {
        Index.visit_f64(v).map(ActionRef::Index)
    }

    fn visit_str<E: de::Error>(self, v: &str) -> Result<ActionRef, E> {
        Ok(ActionRef::Name(v.to_owned()))
    }
}

/// An array of numbers, `-0.0` read as `0.0`.
struct Numbers;

impl<'de> DeserializeSeed<'de> for Numbers {
    type Value = Vec<f64>;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<Vec<f64>, D::Error> {
        d.deserialize_seq(self)
    }
}

impl<'de> Visitor<'de> for Numbers {
    type Value = Vec<f64>;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("an array of numbers")
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<f64>, A::Error> {
        let mut out = Vec::new();
        while let Some(x) = seq.next_element_seed(Number)? {
            out.push(x);
        }
        Ok(out)
    }
}

struct Number;

impl<'de> DeserializeSeed<'de> for Number {
    type Value = f64;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<f64, D::Error> {
        d.deserialize_any(self)
    }
}

impl Visitor<'_> for Number {
    type Value = f64;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("a number")
    }

    fn visit_u64<E: de::Error>(self, v: u64) -> Result<f64, E> {
        Ok(v as f64)
    }

    fn visit_i64<E: de::Error>(self, v: i64) -> Result<f64, E> {
        Ok(v as f64)
    }

    fn visit_f64<E: de::Error>(self, v: f64) -> Result<f64, E> {
        // The slow reader turns an integral float into the integer it
        // equals and back: the same number, except that -0.0 becomes 0.0.
        Ok(if v == 0.0 { 0.0 } else { v })
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;
    use serde_json::json;

    use super::*;

    /// Both readers on one body: the fast one, when it answers, must give
    /// what the slow one gives.
    fn agree(body: &[u8]) -> Result<(), TestCaseError> {
        let slow = slow(body);
        if let Some(fast) = fast(body) {
            let slow = slow.map_err(|e| {
                TestCaseError::fail(format!(
                    "fast took {} but slow refused it: {e}",
                    String::from_utf8_lossy(body)
                ))
            })?;
            prop_assert_eq!(&fast, &slow, "{}", String::from_utf8_lossy(body));
            // Bit for bit, -0.0 and NaN payloads included.
            prop_assert_eq!(format!("{fast:?}"), format!("{slow:?}"));
        }
        Ok(())
    }

    fn one(v: Value) -> ObserveBody {
        fast(v.to_string().as_bytes()).expect("the plain form")
    }

    #[test]
    fn the_plain_forms_take_the_fast_reader() {
        assert_eq!(
            one(json!({"state": 3, "stimulus": [1, 0.5, -0.0], "action_taken": "left"})),
            ObserveBody::One(ObservationIn {
                state: Some(3),
                observation: None,
                stimulus: Some(vec![1.0, 0.5, 0.0]),
                action_taken: Some(ActionRef::Name("left".into())),
                signal: None,
                signal_source: None,
                seq: None,
            })
        );
        assert_eq!(
            one(
                json!({"observations": [{"state": 1.0}, {"state": 2, "action_taken": 1e0, "signal": [1], "signal_source": null}]})
            ),
            ObserveBody::Batch(vec![
                ObservationIn {
                    state: Some(1),
                    observation: None,
                    stimulus: None,
                    action_taken: None,
                    signal: None,
                    signal_source: None,
                    seq: None,
                },
                ObservationIn {
                    state: Some(2),
                    observation: None,
                    stimulus: None,
                    action_taken: Some(ActionRef::Index(1)),
                    signal: Some(vec![1.0]),
                    signal_source: None,
                    seq: None,
                },
            ])
        );
        assert_eq!(one(json!({"observations": []})), ObserveBody::Batch(vec![]));
        // A continuous world's observation; neither `state` nor
        // `observation` is the service's to refuse, with the session's
        // model at hand.
        assert_eq!(
            one(json!({"observation": [0.25, -0.0, 1e3], "stimulus": [0]})),
            ObserveBody::One(ObservationIn {
                state: None,
                observation: Some(vec![0.25, 0.0, 1000.0]),
                stimulus: Some(vec![0.0]),
                action_taken: None,
                signal: None,
                signal_source: None,
                seq: None,
            })
        );
        assert!(matches!(
            one(json!({})),
            ObserveBody::One(ObservationIn {
                state: None,
                observation: None,
                ..
            })
        ));
    }

    #[test]
    fn anything_else_goes_to_the_slow_reader_and_its_messages() {
        for (body, message) in [
            (&b"[25]"[..], "the body must be a JSON object"),
            (
                br#"{"observations": [[25]]}"#,
                "`observations.0`: must be a JSON object",
            ),
            (br#"{"state": 1, "state": 2"#, "malformed JSON body"),
            (
                br#"{"state": 1, "extra": 2}"#,
                "malformed observation: unknown field `extra`",
            ),
            (
                br#"{"state": 1.5}"#,
                "malformed observation: invalid type: floating point `1.5`",
            ),
            (
                br#"{"state": -1}"#,
                "malformed observation: invalid value: integer `-1`",
            ),
            (
                br#"{"state": 1, "observations": []}"#,
                "malformed observation: unknown field `state`",
            ),
            (
                br#"{"observations": null}"#,
                "malformed observation: invalid type: null",
            ),
            (b"", "malformed JSON body"),
            (
                br#"{"state": 1, "seq": -1}"#,
                "`seq` must be an integer from 0 to 18446744073709551615 (the observation's index in the session's stream), not the negative number -1",
            ),
            (
                br#"{"state": 1, "seq": 2.5}"#,
                "`seq` must be an integer from 0 to 18446744073709551615 (the observation's index in the session's stream), not the fractional number 2.5",
            ),
            (
                br#"{"state": 1, "seq": 18446744073709551616}"#,
                "not 18446744073709552000, beyond 2^64 - 1",
            ),
            (br#"{"state": 1, "seq": "3"}"#, "not the string \"3\""),
            (
                br#"{"observations": [{"state": 1, "seq": true}]}"#,
                "not the boolean true",
            ),
        ] {
            assert!(fast(body).is_none(), "{}", String::from_utf8_lossy(body));
            let e = parse(body).expect_err("refused").to_string();
            assert!(
                e.contains(message),
                "{}: {e}",
                String::from_utf8_lossy(body)
            );
        }
        // Accepted by the slow reader only: a duplicate key (the last wins)
        // and an escaped key.
        assert!(fast(br#"{"state": 1, "state": 2}"#).is_none());
        assert!(matches!(
            parse(br#"{"state": 1, "state": 2}"#),
            Ok(ObserveBody::One(ObservationIn { state: Some(2), .. }))
        ));
        // An integral float is the integer, as for every number.
        assert!(matches!(
            parse(br#"{"state": 1, "seq": 7.0}"#),
            Ok(ObserveBody::One(ObservationIn { seq: Some(7), .. }))
        ));
        assert!(matches!(
            fast(br#"{"state": 1, "seq": 18446744073709551615}"#),
            Some(ObserveBody::One(ObservationIn {
                seq: Some(u64::MAX),
                ..
            }))
        ));
        assert!(fast(br#"{"st\u0061te": 4}"#).is_none());
        assert!(matches!(
            parse(br#"{"st\u0061te": 4}"#),
            Ok(ObserveBody::One(ObservationIn { state: Some(4), .. }))
        ));
    }

    fn number() -> impl Strategy<Value = String> {
        prop_oneof![
            any::<u64>().prop_map(|n| n.to_string()),
            any::<i64>().prop_map(|n| n.to_string()),
            any::<f64>()
                .prop_filter("finite", |x| x.is_finite())
                .prop_map(|x| format!("{x:?}")),
            (0u32..40).prop_map(|n| format!("{n}.0")),
            (0u32..25).prop_map(|e| format!("1e{e}")),
            Just("-0.0".to_string()),
            Just("-0".to_string()),
            Just("18446744073709551616.0".to_string()),
            Just("1e400".to_string()),
        ]
    }

    fn value() -> impl Strategy<Value = String> {
        let leaf = prop_oneof![
            number(),
            Just("null".to_string()),
            Just("true".to_string()),
            Just(r#""left""#.to_string()),
            Just("{}".to_string()),
        ];
        leaf.prop_recursive(2, 12, 4, |inner| {
            prop::collection::vec(inner, 0..4).prop_map(|xs| format!("[{}]", xs.join(",")))
        })
    }

    fn key() -> impl Strategy<Value = String> {
        prop_oneof![
            Just("state"),
            Just("observation"),
            Just("stimulus"),
            Just("action_taken"),
            Just("signal"),
            Just("signal_source"),
            Just("seq"),
            Just("observations"),
            Just("other"),
        ]
        .prop_map(|k| format!("\"{k}\""))
    }

    fn object(values: BoxedStrategy<String>) -> impl Strategy<Value = String> {
        prop::collection::vec((key(), values), 0..5).prop_map(|kv| {
            let fields: Vec<String> = kv.into_iter().map(|(k, v)| format!("{k}:{v}")).collect();
            format!("{{{}}}", fields.join(","))
        })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(3000))]

        #[test]
        fn the_readers_agree_on_generated_bodies(
            body in prop_oneof![
                object(value().boxed()),
                object(prop_oneof![
                    value(),
                    prop::collection::vec(object(value().boxed()), 0..3)
                        .prop_map(|xs| format!("[{}]", xs.join(","))),
                ].boxed()),
            ],
        ) {
            agree(body.as_bytes())?;
        }

        #[test]
        fn the_readers_agree_on_observations_with_any_numbers(
            state in number(),
            stimulus in prop::collection::vec(number(), 0..4),
            action in prop_oneof![number(), Just(r#""up""#.to_string())],
        ) {
            let body = format!(
                r#"{{"state":{state},"stimulus":[{}],"action_taken":{action}}}"#,
                stimulus.join(",")
            );
            agree(body.as_bytes())?;
            let batch = format!(r#"{{"observations":[{body},{body}]}}"#);
            agree(batch.as_bytes())?;
        }
    }
}
