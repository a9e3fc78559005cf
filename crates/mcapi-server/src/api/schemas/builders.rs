//! The small builders every request schema is made of: typed numbers
//! and integers with their bounds, arrays, closed objects (serde's
//! `deny_unknown_fields`), names, references, and one builder that turns an
//! entry of the parameter tables into its schema.

use utoipa::openapi::schema::{
    AdditionalProperties, ArrayBuilder, ArrayItems, ObjectBuilder, OneOfBuilder, Schema,
    SchemaType, Type,
};
use utoipa::openapi::{Ref, RefOr};

pub(super) use mcapi_core::params::Bound;

/// Largest JSON integer the server reads into a `u64`/`usize`.
pub(super) const U64_MAX: u64 = u64::MAX;

/// Characters Rust's `str::trim` removes (Unicode `White_Space`), as a
/// regular-expression class body that ECMA-262 and Python both read.
pub(super) const WHITE_SPACE: &str =
    r"\t-\r \x85\xa0\u1680\u2000-\u200a\u2028\u2029\u202f\u205f\u3000";

pub(super) fn reference(name: &str) -> RefOr<Schema> {
    Ref::from_schema_name(name).into()
}

/// `$ref`, or `null` (a field the server reads as absent when null).
pub(super) fn nullable_ref(name: &str, description: &str) -> RefOr<Schema> {
    OneOfBuilder::new()
        .item(ObjectBuilder::new().schema_type(Type::Null))
        .item(reference(name))
        .description(Some(description))
        .into()
}

pub(super) fn typed(t: Type, nullable: bool) -> ObjectBuilder {
    if nullable {
        ObjectBuilder::new().schema_type(SchemaType::from_iter([t, Type::Null]))
    } else {
        ObjectBuilder::new().schema_type(t)
    }
}

/// An integer in `min..=max`.
pub(super) fn integer(min: u64, max: u64, nullable: bool, description: &str) -> ObjectBuilder {
    typed(Type::Integer, nullable)
        .minimum(Some(as_number(min)))
        .maximum(Some(as_number(max)))
        .description(Some(description))
}

pub(super) fn as_number(x: u64) -> utoipa::Number {
    utoipa::Number::UInt(usize::try_from(x).unwrap_or(usize::MAX))
}

pub(super) fn number(
    lower: Bound,
    upper: Bound,
    nullable: bool,
    description: &str,
) -> ObjectBuilder {
    let mut o = typed(Type::Number, nullable).description(Some(description));
    o = match lower {
        Bound::Incl(x) => o.minimum(Some(x)),
        Bound::Excl(x) => o.exclusive_minimum(Some(x)),
        Bound::None => o,
    };
    match upper {
        Bound::Incl(x) => o.maximum(Some(x)),
        Bound::Excl(x) => o.exclusive_maximum(Some(x)),
        Bound::None => o,
    }
}

pub(super) fn array(
    items: impl Into<RefOr<Schema>>,
    min: usize,
    max: usize,
    nullable: bool,
    description: &str,
) -> ArrayBuilder {
    let a = ArrayBuilder::new()
        .items(ArrayItems::RefOrSchema(Box::new(items.into())))
        .min_items((min > 0).then_some(min))
        .max_items(Some(max))
        .description(Some(description));
    if nullable {
        a.schema_type(SchemaType::from_iter([Type::Array, Type::Null]))
    } else {
        a
    }
}

/// An object that takes only the properties listed (serde's
/// `deny_unknown_fields`).
pub(super) fn closed(description: &str) -> ObjectBuilder {
    ObjectBuilder::new()
        .schema_type(Type::Object)
        .additional_properties(Some(AdditionalProperties::<Schema>::FreeForm(false)))
        .description(Some(description))
}

/// A name (action, stimulus, state) of at most `max_bytes` bytes of UTF-8.
/// `maxLength` counts characters: an ASCII name may have `max_bytes` of
/// them, others fewer (the server counts bytes and answers 413 beyond).
pub(super) fn name(max_bytes: usize, description: &str) -> ObjectBuilder {
    typed(Type::String, false)
        .max_length(Some(max_bytes))
        .description(Some(format!(
            "{description} (limit: at most {max_bytes} bytes of UTF-8)"
        )))
}

/// A [`name`] with at least one character that is not white space.
pub(super) fn non_blank_name(max_bytes: usize, description: &str) -> ObjectBuilder {
    name(max_bytes, description).pattern(Some(format!("[^{WHITE_SPACE}]")))
}
