//! Space bounds in JSON, which has no infinity: `serde_json` writes an
//! infinite `f32` as `null` and then cannot read it back as a number, so a
//! checkpoint of an environment with unbounded observations (Point, Car)
//! could be written but not loaded. With `#[serde(with = "...::lower")]` (or
//! `upper`) infinite bounds are written as the strings `"-inf"` / `"inf"`;
//! reading accepts numbers, those strings, and `null` (what checkpoints
//! written before this fix hold), which becomes -inf for a lower bound and
//! +inf for an upper one: the only infinity a bound of that side can be.

use serde::de::Error as _;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

#[derive(Serialize, Deserialize)]
#[serde(untagged)]
enum Bound {
    Finite(f32),
    Named(String),
}

fn serialize<S: Serializer>(v: &[f32], s: S) -> Result<S::Ok, S::Error> {
    v.iter()
        .map(|&x| match x {
            f32::INFINITY => Bound::Named("inf".into()),
            f32::NEG_INFINITY => Bound::Named("-inf".into()),
            x if x.is_nan() => Bound::Named("nan".into()),
            x => Bound::Finite(x),
        })
        .collect::<Vec<_>>()
        .serialize(s)
}

fn deserialize<'de, D: Deserializer<'de>>(d: D, null: f32) -> Result<Vec<f32>, D::Error> {
    Vec::<Option<Bound>>::deserialize(d)?
        .into_iter()
        .map(|b| match b {
            None => Ok(null),
            Some(Bound::Finite(x)) => Ok(x),
            Some(Bound::Named(t)) => match t.as_str() {
                "inf" => Ok(f32::INFINITY),
                "-inf" => Ok(f32::NEG_INFINITY),
                "nan" => Ok(f32::NAN),
                other => Err(D::Error::custom(format!(
                    "bound {other:?}: expected a number, \"inf\" or \"-inf\""
                ))),
            },
        })
        .collect()
}

/// Lower bounds: `null` reads as -inf.
pub mod lower {
    use super::*;

    pub fn serialize<S: Serializer>(v: &[f32], s: S) -> Result<S::Ok, S::Error> {
        super::serialize(v, s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<f32>, D::Error> {
        super::deserialize(d, f32::NEG_INFINITY)
    }
}

/// Upper bounds: `null` reads as +inf.
pub mod upper {
    use super::*;

    pub fn serialize<S: Serializer>(v: &[f32], s: S) -> Result<S::Ok, S::Error> {
        super::serialize(v, s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<f32>, D::Error> {
        super::deserialize(d, f32::INFINITY)
    }
}

#[cfg(test)]
mod tests {
    use serde::{Deserialize, Serialize};

    #[derive(Debug, PartialEq, Serialize, Deserialize)]
    struct Box2 {
        #[serde(with = "super::lower")]
        low: Vec<f32>,
        #[serde(with = "super::upper")]
        high: Vec<f32>,
    }

    #[test]
    fn infinite_bounds_round_trip_and_old_nulls_read_as_infinities() {
        let b = Box2 {
            low: vec![f32::NEG_INFINITY, -1.0],
            high: vec![f32::INFINITY, 1.0],
        };
        let text = serde_json::to_string(&b).unwrap();
        assert_eq!(text, r#"{"low":["-inf",-1.0],"high":["inf",1.0]}"#);
        assert_eq!(serde_json::from_str::<Box2>(&text).unwrap(), b);
        // What serde_json wrote before: null for every infinity.
        let old = r#"{"low":[null,-1.0],"high":[null,1.0]}"#;
        assert_eq!(serde_json::from_str::<Box2>(old).unwrap(), b);
        assert!(serde_json::from_str::<Box2>(r#"{"low":["big"],"high":[1]}"#).is_err());
    }
}
