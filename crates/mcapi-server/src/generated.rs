//! The files written from the parameter tables (the core's
//! [`AGENT_PARAMS`] and [`CURIOSITY_PARAMS`], the service's
//! [`SESSION_PARAMS`]), and the checks that keep the rest of the house in
//! step with them:
//!
//! - `docs/sessions.md`: the two tables of parameters, between
//!   `<!-- params:NAME -->` markers;
//! - `clients/python/mcapi_client/_params.py`: the Python client's one
//!   options type, `AgentKwargs`, and the names of the curiosity constants.
//!
//! Both are written by `make generate` (this module's tests with
//! `MCAPI_BLESS=1`), and the tests fail while a committed file differs from
//! what the tables give. The proto is not generated (it is the source of
//! the gRPC code): its test checks that `SessionConfig` and
//! `EffectiveConfig` have one field of the right type per entry, in order.
//! The OpenAPI document is built from the tables at start-up
//! ([`crate::api::schemas`]); its test checks the built document.
//!
//! [`SESSION_PARAMS`]: crate::service::agent_config::SESSION_PARAMS

use std::fmt::Write as _;

use mcapi_core::params::spec::Default;
use mcapi_core::params::{CURIOSITY_PARAMS, Kind, Param};

use crate::service::agent_config::session_options;

/// The Markdown table of these parameters, as docs/sessions.md has it.
pub fn markdown_table(params: &[&Param]) -> String {
    let mut out =
        String::from("| field | default | allowed | meaning |\n| --- | --- | --- | --- |\n");
    for p in params {
        let default = match p.default {
            Default::Name(n) => format!("`\"{n}\"`"),
            Default::Integer(_) | Default::Real(_) if !p.unit.is_empty() => {
                format!("{} {}", p.default_text(), p.unit)
            }
            _ => p.default_text(),
        };
        let meaning = if p.see.is_empty() {
            p.doc.to_owned()
        } else {
            format!("{} ([more]({}))", p.doc, p.see)
        };
        let _ = writeln!(
            out,
            "| `{}` | {default} | {} | {} |",
            p.name,
            p.allowed().replace('|', "\\|"),
            meaning.replace('|', "\\|")
        );
    }
    out
}

/// Greek letters as Python's docstrings spell them (ruff flags letters
/// that look like Latin ones).
fn ascii(text: &str) -> String {
    const GREEK: [(char, &str); 13] = [
        ('η', "eta"),
        ('γ', "gamma"),
        ('ρ', "rho"),
        ('Ξ', "Xi"),
        ('ξ', "xi"),
        ('σ', "sigma"),
        ('λ', "lambda"),
        ('Λ', "Lambda"),
        ('ε', "epsilon"),
        ('β', "beta"),
        ('τ', "tau"),
        ('δ', "delta"),
        ('≤', "<="),
    ];
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match GREEK.iter().find(|(g, _)| *g == c) {
            Some((_, name)) => out.push_str(name),
            None => out.push(c),
        }
    }
    out.replace('`', "\"")
}

/// `text` in lines of at most `width` characters (words are not split),
/// each starting with `indent`.
fn wrap(text: &str, indent: &str, width: usize) -> String {
    let mut out = String::new();
    let mut line = String::from(indent);
    for word in text.split(' ') {
        if line.len() > indent.len() && line.len() + 1 + word.len() > width {
            out.push_str(line.trim_end());
            out.push('\n');
            line = String::from(indent);
        }
        if line.len() > indent.len() {
            line.push(' ');
        }
        line.push_str(word);
    }
    out.push_str(&line);
    out.push('\n');
    out
}

/// The Python annotation of a parameter's option (the client's
/// normalisers key on it: mcapi_client/types.py).
fn python_type(p: &Param) -> String {
    match p.kind {
        Kind::Real { .. } => "FloatLike".to_owned(),
        Kind::Integer { .. } => "IntLike".to_owned(),
        Kind::PerStimulus { .. } => "FloatsLike".to_owned(),
        Kind::RealOrName { .. } => format!("{} | FloatLike", p.type_name()),
        Kind::Choice(_) => p.type_name(),
        Kind::Object(schema) => format!("{}Like", schema.trim_end_matches("Config")),
    }
}

/// `clients/python/mcapi_client/_params.py`.
pub fn python_module() -> String {
    let options: Vec<&Param> = session_options().collect();
    let mut normalise = Vec::new();
    let mut types = Vec::new();
    for p in &options {
        for t in python_type(p).split(" | ") {
            // The number-like aliases live beside their normalisers.
            let list = if ["FloatLike", "FloatsLike", "IntLike"].contains(&t) {
                &mut normalise
            } else {
                &mut types
            };
            if !list.contains(&t.to_owned()) {
                list.push(t.to_owned());
            }
        }
    }
    normalise.sort();
    types.sort();
    let mut out = String::from(
        r#""""The agent options of a session, one per parameter of the server's table.

Generated from the parameter tables of mcapi-core and mcapi-server by
`make generate`; do not edit by hand (a test fails when it differs).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final, TypedDict

if TYPE_CHECKING:
"#,
    );
    let _ = writeln!(out, "    from ._inputs import {}", types.join(", "));
    let _ = writeln!(out, "    from ._normalise import {}", normalise.join(", "));
    out.push_str(
        r#"

class AgentKwargs(TypedDict, total=False):
    """The agent options of ``create_session``; one left out takes the server's default."""

"#,
    );
    for p in &options {
        let mut doc = ascii(p.doc);
        if let Some(first) = doc.get(..1) {
            doc = first.to_uppercase() + &doc[1..];
        }
        let allowed = match p.kind {
            Kind::Real { .. } | Kind::PerStimulus { .. } => {
                format!(", in {}", ascii(&p.allowed()))
            }
            _ => String::new(),
        };
        let _ = writeln!(out, "    {}: {} | None", p.name, python_type(p));
        let text = format!(
            "\"\"\"{doc}{allowed}; default {}.\"\"\"",
            ascii(&p.default_text())
        );
        out.push_str(&wrap(&text, "    ", 100));
    }
    out.push_str("\n\nAGENT_OPTIONS: Final[tuple[str, ...]] = (\n");
    for p in &options {
        let _ = writeln!(out, "    \"{}\",", p.name);
    }
    out.push_str(")\n\"\"\"The keys of :class:`AgentKwargs`, in the server's order.\"\"\"\n\n");
    out.push_str("AGENT_KINDS: Final[dict[str, str]] = {\n");
    for p in &options {
        let kind = match p.kind {
            Kind::Real { .. } => "real",
            Kind::Integer { .. } => "integer",
            Kind::PerStimulus { .. } => "per_stimulus",
            Kind::RealOrName { .. } => "real_or_name",
            Kind::Choice(_) => "choice",
            Kind::Object(_) => "object",
        };
        let _ = writeln!(out, "    \"{}\": \"{kind}\",", p.name);
    }
    out.push_str(
        "}\n\"\"\"What each option holds: \"real\", \"integer\", \"per_stimulus\", \"real_or_name\",\n\"choice\" or \"object\" (the readers of a session's configuration follow it).\"\"\"\n\n",
    );
    out.push_str("CURIOSITY_PARAMS: Final[tuple[str, ...]] = (\n");
    for p in &CURIOSITY_PARAMS {
        let _ = writeln!(out, "    \"{}\",", p.name);
    }
    out.push_str(
        ")\n\"\"\"The constants of a curiosity channel (the keys of ``CuriosityConfig.params``).\"\"\"\n",
    );
    out
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use mcapi_core::params::Max;

    use super::*;
    use crate::api::schemas::agent::describe;

    fn repo(path: &str) -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../..")
            .join(path)
    }

    fn bless() -> bool {
        std::env::var_os("MCAPI_BLESS").is_some_and(|v| v == "1")
    }

    /// Compares a committed file with what the tables give; rewrites it
    /// under `MCAPI_BLESS=1`.
    fn check(path: &str, expected: &str) {
        let file = repo(path);
        let actual = std::fs::read_to_string(&file).unwrap_or_default();
        if actual == expected {
            return;
        }
        if bless() {
            std::fs::write(&file, expected).expect("writes the generated file");
            return;
        }
        let line = actual
            .lines()
            .zip(expected.lines())
            .position(|(a, e)| a != e)
            .unwrap_or_else(|| actual.lines().count().min(expected.lines().count()));
        panic!(
            "{path} differs from the parameter tables from line {} on; run `make generate` \
             and commit the result",
            line + 1
        );
    }

    /// `text` with the part between `<!-- params:NAME -->` and
    /// `<!-- /params:NAME -->` replaced by `table`.
    fn splice(text: &str, name: &str, table: &str) -> String {
        let open = format!("<!-- params:{name} -->\n");
        let close = format!("<!-- /params:{name} -->");
        let start = text.find(&open).expect("the opening marker") + open.len();
        let end = text[start..].find(&close).expect("the closing marker") + start;
        format!("{}{table}{}", &text[..start], &text[end..])
    }

    #[test]
    fn docs_sessions_md_has_the_tables() {
        let path = "docs/sessions.md";
        let text = std::fs::read_to_string(repo(path)).expect("docs/sessions.md");
        let agent: Vec<&Param> = session_options().collect();
        let curiosity: Vec<&Param> = CURIOSITY_PARAMS.iter().collect();
        let text = splice(&text, "agent", &markdown_table(&agent));
        let text = splice(&text, "curiosity", &markdown_table(&curiosity));
        check(path, &text);
    }

    #[test]
    fn the_python_client_has_the_options() {
        check("clients/python/mcapi_client/_params.py", &python_module());
    }

    /// The fields of a proto message: `(name, type)`, a `oneof` as one
    /// field of type `oneof`, in the order written.
    fn proto_fields(proto: &str, message: &str) -> Vec<(String, String)> {
        let head = format!("message {message} {{");
        let start = proto.find(&head).expect("the message") + head.len();
        let mut fields = Vec::new();
        let mut depth = 0;
        for line in proto[start..].lines() {
            let line = line.split("//").next().unwrap_or("").trim();
            if line.starts_with("oneof ") {
                let name = line
                    .trim_start_matches("oneof ")
                    .trim_end_matches('{')
                    .trim();
                fields.push((name.to_owned(), "oneof".to_owned()));
                depth += 1;
                continue;
            }
            if line == "}" {
                if depth == 0 {
                    break;
                }
                depth -= 1;
                continue;
            }
            if depth > 0 || !line.ends_with(';') {
                continue;
            }
            let words: Vec<&str> = line.split_whitespace().collect();
            let (ty, name) = match words.as_slice() {
                ["optional", ty, name, ..] => ((*ty).to_owned(), *name),
                ["repeated", ty, name, ..] => (format!("repeated {ty}"), *name),
                [ty, name, ..] => ((*ty).to_owned(), *name),
                _ => continue,
            };
            fields.push((name.to_owned(), ty));
        }
        fields
    }

    /// One field per option, of the option's type; the text may list them
    /// in any order (a new field is added with the next free number).
    #[test]
    fn the_proto_has_one_field_per_option() {
        let proto =
            std::fs::read_to_string(repo("proto/mcapi/v1/agents.proto")).expect("agents.proto");
        for message in ["SessionConfig", "EffectiveConfig"] {
            let fields = proto_fields(&proto, message);
            let mut names: Vec<&str> = fields.iter().map(|(n, _)| n.as_str()).collect();
            let mut expected: Vec<&str> = session_options().map(|p| p.name).collect();
            names.sort_unstable();
            expected.sort_unstable();
            assert_eq!(names, expected, "the fields of {message}");
            for p in session_options() {
                let want = match p.kind {
                    Kind::Real { .. } => "double".to_owned(),
                    Kind::Integer { .. } => "uint64".to_owned(),
                    Kind::PerStimulus { .. } => "repeated double".to_owned(),
                    Kind::RealOrName { .. } => "oneof".to_owned(),
                    Kind::Choice(_) => p.type_name(),
                    Kind::Object(schema) => schema.to_owned(),
                };
                let ty = fields
                    .iter()
                    .find(|(n, _)| n == p.name)
                    .map(|(_, ty)| ty.as_str());
                assert_eq!(ty, Some(want.as_str()), "{message}.{}", p.name);
            }
        }
    }

    /// The document the server serves agrees with the tables: one property
    /// per entry, each with the entry's bounds and description.
    #[test]
    fn the_openapi_document_has_the_tables() {
        let doc = serde_json::to_value(crate::api::openapi::document(
            &crate::service::Limits::default(),
        ))
        .expect("serialises");
        let schemas = &doc["components"]["schemas"];
        let agent: Vec<&Param> = session_options().collect();
        let curiosity: Vec<&Param> = CURIOSITY_PARAMS.iter().collect();
        for (schema, params) in [("SessionConfig", agent), ("CuriosityParams", curiosity)] {
            let properties = schemas[schema]["properties"]
                .as_object()
                .expect("properties");
            let mut names: Vec<&str> = properties.keys().map(String::as_str).collect();
            let mut expected: Vec<&str> = params.iter().map(|p| p.name).collect();
            names.sort_unstable();
            expected.sort_unstable();
            assert_eq!(names, expected, "the properties of {schema}");
            for p in params {
                let property = &properties[p.name];
                assert_eq!(
                    property["description"].as_str(),
                    Some(describe(p).as_str()),
                    "{schema}.{}",
                    p.name
                );
                if let Kind::Integer { min, max } = p.kind {
                    assert_eq!(property["minimum"].as_u64(), Some(min), "{}", p.name);
                    if let Max::Value(v) = max {
                        assert_eq!(property["maximum"].as_u64(), Some(v), "{}", p.name);
                    }
                }
            }
        }
    }
}
