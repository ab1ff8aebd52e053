//! TOML documents: parsing into typed settings with errors that name the file and the line,
//! and the key names a settings type accepts.

use std::path::Path;

use serde::de::{self, DeserializeOwned, Visitor};

use crate::error::{Error, Result};

/// Parses a TOML document into `T`; an error names `origin` and the line (unknown keys
/// included, where `T` denies them).
pub fn parse<T: DeserializeOwned>(text: &str, origin: &Path) -> Result<T> {
    toml::from_str(text).map_err(|e| {
        let at = e
            .span()
            .map(|s| format!("line {}: ", error_line(text, s, e.message())))
            .unwrap_or_default();
        Error::format(origin, format!("{at}{}", e.message()))
    })
}

/// The line of an error in `text`: where its span starts, or, when the span covers a whole
/// table (an error about one of its keys found after the table was read), the line of the key
/// the message names first (in backticks).
fn error_line(text: &str, span: std::ops::Range<usize>, message: &str) -> usize {
    let line_of = |at: usize| text[..at.min(text.len())].matches('\n').count() + 1;
    let start = span.start.min(text.len());
    let end = span.end.clamp(start, text.len());
    let within = &text[start..end];
    if within.contains('\n') {
        let key = message.split('`').nth(1).filter(|k| !k.is_empty());
        if let Some(key) = key {
            let mut offset = start;
            for line in within.split_inclusive('\n') {
                let named = line
                    .trim_start()
                    .strip_prefix(key)
                    .is_some_and(|rest| rest.trim_start().starts_with('='));
                if named {
                    return line_of(offset);
                }
                offset += line.len();
            }
        }
    }
    line_of(start)
}

/// The keys a settings type (a struct deriving `Deserialize`, without flattened fields)
/// accepts, in the order it declares them.
pub fn keys<T: DeserializeOwned>() -> &'static [&'static str] {
    let mut found = None;
    let _ = T::deserialize(KeyCatcher(&mut found));
    found.unwrap_or(&[])
}

/// A deserializer that only records the field names a struct asks for.
struct KeyCatcher<'a>(&'a mut Option<&'static [&'static str]>);

impl<'de> de::Deserializer<'de> for KeyCatcher<'_> {
    type Error = de::value::Error;

    fn deserialize_any<V: Visitor<'de>>(self, _: V) -> std::result::Result<V::Value, Self::Error> {
        Err(de::Error::custom("not a struct"))
    }

    fn deserialize_struct<V: Visitor<'de>>(
        self,
        _name: &'static str,
        fields: &'static [&'static str],
        _visitor: V,
    ) -> std::result::Result<V::Value, Self::Error> {
        *self.0 = Some(fields);
        Err(de::Error::custom("keys recorded"))
    }

    serde::forward_to_deserialize_any! {
        bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string bytes byte_buf
        option unit unit_struct newtype_struct seq tuple tuple_struct map enum identifier
        ignored_any
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Two {
        first: u8,
        #[serde(rename = "second_key")]
        second: String,
    }

    #[test]
    fn keys_in_declared_order() {
        assert_eq!(keys::<Two>(), &["first", "second_key"]);
        assert!(keys::<u8>().is_empty());
    }

    #[test]
    fn an_error_about_a_key_of_a_table_points_at_the_key() {
        let text = "[t]\na = 1\n  bee = 2\nc = 3\n";
        let t = text.find("[t]").unwrap();
        assert_eq!(error_line(text, t..text.len(), "unknown field `bee`"), 3);
        assert_eq!(error_line(text, t..text.len(), "`c`: bad"), 4);
        // A key not in the table, or no key: where the span starts.
        assert_eq!(error_line(text, t..text.len(), "unknown field `zz`"), 1);
        assert_eq!(error_line(text, 4..5, "unknown field `bee`"), 2);
        let err = parse::<Two>("first = 1\nsecond = \"x\"\n", Path::new("x.toml"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("line 2") && err.contains("second"), "{err}");
    }
}
