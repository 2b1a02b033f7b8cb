//! JSON schemas of our own MCAP topics (`rover_twin.*`: blackboard slots, messages, module reports,
//! the score), written in the subset of JSON Schema that Foxglove's viewers turn into message
//! definitions (Foxglove Studio's and Lichtblick's `parseJsonSchema`): every property has one
//! `type` among boolean, string, number, integer, object (with `properties`) and array (with
//! `items` of one of those but array). A property outside that subset makes the viewer refuse the
//! whole topic, so what cannot be said in it is left undescribed (JSON Schema allows properties
//! a schema does not name) rather than described loosely.
//!
//! A slot's value has one Rust type, but the logger only sees it as JSON: its schema is inferred
//! from the topic's first message ([`infer`]): fields null there (an `Option` still unset) and
//! empty arrays are left undescribed, the elements of an array are described by the union of
//! their fields, each where they agree on its type. A null value stands for an unset one anywhere
//! (the subset cannot say "nullable"; Foxglove shows a null field as missing).
//! `scripts/validate_logs.py` validates every message of a run against its topic's schema, nulls
//! taken as absent.

use serde_json::{Map, Value, json};

/// The schema of a topic named `title` whose messages are objects with `properties` (a JSON
/// object of field schemas).
pub(super) fn object(title: &str, description: &str, properties: Value) -> String {
    json!({ "title": title, "description": description, "type": "object", "properties": properties })
        .to_string()
}

/// The schema of a topic named `title` inferred from its first message `first` (an object).
pub(super) fn inferred(title: &str, description: &str, first: &Value) -> String {
    match infer(first) {
        Some(Value::Object(mut s)) if s.get("type") == Some(&json!("object")) => {
            s.insert("title".into(), json!(title));
            s.insert("description".into(), json!(description));
            Value::Object(s).to_string()
        }
        _ => object(title, description, json!({})),
    }
}

/// An object whose fields are not described (their shapes vary from message to message).
pub(super) fn open_object() -> Value {
    json!({ "type": "object", "properties": {} })
}

/// The schema `value` has in the subset above, or `None` where it cannot be said from this value
/// (null, an empty array, an array of arrays).
pub(super) fn infer(value: &Value) -> Option<Value> {
    match value {
        Value::Null => None,
        Value::Bool(_) => Some(json!({ "type": "boolean" })),
        Value::Number(n) if n.is_f64() => Some(json!({ "type": "number" })),
        Value::Number(_) => Some(json!({ "type": "integer" })),
        Value::String(_) => Some(json!({ "type": "string" })),
        Value::Object(fields) => {
            let properties: Map<String, Value> =
                fields.iter().filter_map(|(k, v)| Some((k.clone(), infer(v)?))).collect();
            Some(json!({ "type": "object", "properties": properties }))
        }
        Value::Array(items) => {
            let mut shared: Option<Value> = None;
            for item in items.iter().filter(|v| !v.is_null()) {
                let s = infer(item)?;
                shared = Some(match shared {
                    None => s,
                    Some(prev) => merge(prev, s)?,
                });
            }
            let items = shared?;
            (items["type"] != "array").then(|| json!({ "type": "array", "items": items }))
        }
    }
}

/// One schema for two elements of an array: their type (a number where one is an integer and the
/// other fractional), and for objects the union of their fields, a field in both described only
/// where both agree on its type; `None` when the types differ.
fn merge(a: Value, b: Value) -> Option<Value> {
    if a["type"] != b["type"] {
        // An integer field that is fractional elsewhere is a number.
        let numeric = |s: &Value| s["type"] == "integer" || s["type"] == "number";
        return (numeric(&a) && numeric(&b)).then(|| json!({ "type": "number" }));
    }
    match (a, b) {
        (Value::Object(mut a), Value::Object(mut b)) if a.get("type") == Some(&json!("object")) => {
            let (Some(Value::Object(pa)), Some(Value::Object(mut pb))) =
                (a.remove("properties"), b.remove("properties"))
            else {
                return None;
            };
            let mut properties = Map::new();
            for (k, sa) in pa {
                match pb.remove(&k) {
                    Some(sb) => {
                        if let Some(s) = merge(sa, sb) {
                            properties.insert(k, s);
                        }
                    }
                    None => {
                        properties.insert(k, sa);
                    }
                }
            }
            properties.extend(pb);
            Some(json!({ "type": "object", "properties": properties }))
        }
        (Value::Object(mut a), Value::Object(mut b)) if a.get("type") == Some(&json!("array")) => {
            let items = merge(a.remove("items")?, b.remove("items")?)?;
            Some(json!({ "type": "array", "items": items }))
        }
        (a, _) => Some(a),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What Foxglove's `parseJsonSchema` accepts: each property one supported type, objects with
    /// properties, arrays with items that are no arrays.
    fn foxglove_reads(s: &Value) -> bool {
        match s["type"].as_str() {
            Some("boolean" | "string" | "number" | "integer") => true,
            Some("object") => s["properties"].as_object().is_some_and(|p| p.values().all(foxglove_reads)),
            Some("array") => s["items"]["type"] != "array" && foxglove_reads(&s["items"]),
            _ => false,
        }
    }

    #[test]
    fn a_slot_value_is_described_by_its_fields_with_unset_and_empty_ones_left_out() {
        let v = json!({
            "seq": 3, "stamp": 100, "value": {
                "mode": "idle", "goal": null, "speed": 0.5, "ok": true, "path": [],
                "covariance": [0.1, 0.0, 2.0], "grid": [[1, 2], [3, 4]],
                "joints": [{ "name": "a", "position": 0.1, "fault": null }, { "name": "b", "position": 1, "fault": "stall" }],
            }
        });
        let s: Value = serde_json::from_str(&inferred("rover_twin.Slot<T>", "a slot", &v)).unwrap();
        assert_eq!(s["title"], "rover_twin.Slot<T>");
        assert!(foxglove_reads(&s), "{s}");
        let p = &s["properties"]["value"]["properties"];
        assert_eq!(p["mode"]["type"], "string");
        assert_eq!(p["speed"]["type"], "number");
        assert_eq!(s["properties"]["seq"]["type"], "integer");
        assert_eq!(p["covariance"]["items"]["type"], "number");
        for undescribed in ["goal", "path", "grid"] {
            assert!(p.get(undescribed).is_none(), "{undescribed}: {}", p[undescribed]);
        }
        let joint = &p["joints"]["items"]["properties"];
        assert_eq!(joint["position"]["type"], "number", "an integer in one element, fractional in another");
        assert_eq!(joint["fault"]["type"], "string", "null in one element, a string in another");
    }

    #[test]
    fn elements_that_disagree_on_a_field_leave_it_undescribed_and_on_their_type_the_array() {
        let v = json!({ "a": [{ "x": 1, "y": "s" }, { "x": "t", "y": "u" }], "b": [1, "two"] });
        let s = infer(&v).unwrap();
        assert!(foxglove_reads(&s), "{s}");
        assert!(s["properties"]["a"]["items"]["properties"].get("x").is_none());
        assert_eq!(s["properties"]["a"]["items"]["properties"]["y"]["type"], "string");
        assert!(s["properties"].get("b").is_none());
    }

    #[test]
    fn a_value_that_is_no_object_gives_an_object_schema_with_no_fields() {
        let s: Value = serde_json::from_str(&inferred("t", "d", &json!([1, 2]))).unwrap();
        assert_eq!(s["type"], "object");
        assert!(foxglove_reads(&s));
        assert!(foxglove_reads(&open_object()));
    }
}
