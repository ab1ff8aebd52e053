//! The ONNX protobuf messages a model needs, declared by hand with `prost` (no `protoc`, no build
//! script), and small builders for nodes, attributes and initializers.
//!
//! Field numbers follow `onnx/onnx.proto` (ONNX 1.23). Only the fields this crate writes or reads
//! are declared; a decoder skips the others. `onnx.proto` is proto2, so scalars whose zero value is
//! meaningful (an attribute's `i`, a tensor's `data_type`) are `Option`s and are written even when
//! zero; proto2 `repeated` scalars that are not declared packed are written unpacked.

use std::io::Write;

use super::write_counted;

/// The ONNX operator set the project's graphs use.
pub const OPSET: i64 = 17;
/// The ONNX IR version written.
pub const IR_VERSION: i64 = 8;
/// `TensorProto.DataType.FLOAT`.
pub const FLOAT: i32 = 1;
/// `TensorProto.DataType.INT64`.
pub const INT64: i32 = 7;

/// `AttributeProto.AttributeType` values used here.
pub mod attribute_type {
    /// A single float (`f`).
    pub const FLOAT: i32 = 1;
    /// A single integer (`i`).
    pub const INT: i32 = 2;
    /// A byte string (`s`).
    pub const STRING: i32 = 3;
    /// A list of floats (`floats`).
    pub const FLOATS: i32 = 6;
    /// A list of integers (`ints`).
    pub const INTS: i32 = 7;
}

/// `ModelProto`: the top-level message of an `.onnx` file.
#[derive(Clone, PartialEq, prost::Message)]
pub struct ModelProto {
    /// The IR version (8 for this crate's models).
    #[prost(int64, optional, tag = "1")]
    pub ir_version: Option<i64>,
    /// The operator sets the graph uses.
    #[prost(message, repeated, tag = "8")]
    pub opset_import: Vec<OperatorSetIdProto>,
    /// The tool that wrote the model.
    #[prost(string, optional, tag = "2")]
    pub producer_name: Option<String>,
    /// Its version.
    #[prost(string, optional, tag = "3")]
    pub producer_version: Option<String>,
    /// A reverse-DNS namespace for the model.
    #[prost(string, optional, tag = "4")]
    pub domain: Option<String>,
    /// The model's own version.
    #[prost(int64, optional, tag = "5")]
    pub model_version: Option<i64>,
    /// Free text.
    #[prost(string, optional, tag = "6")]
    pub doc_string: Option<String>,
    /// The computation.
    #[prost(message, optional, tag = "7")]
    pub graph: Option<GraphProto>,
    /// Named strings (provenance, options).
    #[prost(message, repeated, tag = "14")]
    pub metadata_props: Vec<StringStringEntryProto>,
}

/// `OperatorSetIdProto`: an operator set and its version.
#[derive(Clone, PartialEq, prost::Message)]
pub struct OperatorSetIdProto {
    /// The domain; empty for the default `ai.onnx`.
    #[prost(string, optional, tag = "1")]
    pub domain: Option<String>,
    /// The opset version.
    #[prost(int64, optional, tag = "2")]
    pub version: Option<i64>,
}

/// `StringStringEntryProto`: a key and a value.
#[derive(Clone, PartialEq, prost::Message)]
pub struct StringStringEntryProto {
    /// The key.
    #[prost(string, optional, tag = "1")]
    pub key: Option<String>,
    /// The value.
    #[prost(string, optional, tag = "2")]
    pub value: Option<String>,
}

/// `GraphProto`: nodes, initializers, inputs and outputs.
#[derive(Clone, PartialEq, prost::Message)]
pub struct GraphProto {
    /// The nodes, in a topological order.
    #[prost(message, repeated, tag = "1")]
    pub node: Vec<NodeProto>,
    /// The graph's name.
    #[prost(string, optional, tag = "2")]
    pub name: Option<String>,
    /// Constant tensors (weights).
    #[prost(message, repeated, tag = "5")]
    pub initializer: Vec<TensorProto>,
    /// Free text.
    #[prost(string, optional, tag = "10")]
    pub doc_string: Option<String>,
    /// The graph's inputs.
    #[prost(message, repeated, tag = "11")]
    pub input: Vec<ValueInfoProto>,
    /// The graph's outputs.
    #[prost(message, repeated, tag = "12")]
    pub output: Vec<ValueInfoProto>,
    /// Types of intermediate values (optional).
    #[prost(message, repeated, tag = "13")]
    pub value_info: Vec<ValueInfoProto>,
}

/// `NodeProto`: one operator application.
#[derive(Clone, PartialEq, prost::Message)]
pub struct NodeProto {
    /// Input value names; an empty name skips an optional input.
    #[prost(string, repeated, tag = "1")]
    pub input: Vec<String>,
    /// Output value names.
    #[prost(string, repeated, tag = "2")]
    pub output: Vec<String>,
    /// The node's name.
    #[prost(string, optional, tag = "3")]
    pub name: Option<String>,
    /// The operator (`Conv`, `Relu`, ...).
    #[prost(string, optional, tag = "4")]
    pub op_type: Option<String>,
    /// The operator's domain; empty for `ai.onnx`.
    #[prost(string, optional, tag = "7")]
    pub domain: Option<String>,
    /// The operator's attributes.
    #[prost(message, repeated, tag = "5")]
    pub attribute: Vec<AttributeProto>,
    /// Free text.
    #[prost(string, optional, tag = "6")]
    pub doc_string: Option<String>,
}

/// `AttributeProto`: a named attribute value of a node.
#[derive(Clone, PartialEq, prost::Message)]
pub struct AttributeProto {
    /// The attribute's name.
    #[prost(string, optional, tag = "1")]
    pub name: Option<String>,
    /// Which value field is used (see [`attribute_type`]).
    #[prost(int32, optional, tag = "20")]
    pub r#type: Option<i32>,
    /// A float value.
    #[prost(float, optional, tag = "2")]
    pub f: Option<f32>,
    /// An integer value.
    #[prost(int64, optional, tag = "3")]
    pub i: Option<i64>,
    /// A byte-string value.
    #[prost(bytes = "vec", optional, tag = "4")]
    pub s: Option<Vec<u8>>,
    /// A list of floats.
    #[prost(float, repeated, packed = "false", tag = "7")]
    pub floats: Vec<f32>,
    /// A list of integers.
    #[prost(int64, repeated, packed = "false", tag = "8")]
    pub ints: Vec<i64>,
}

/// `TensorProto`: a constant tensor, here always with `raw_data`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct TensorProto {
    /// The shape.
    #[prost(int64, repeated, packed = "false", tag = "1")]
    pub dims: Vec<i64>,
    /// The element type ([`FLOAT`], [`INT64`], ...).
    #[prost(int32, optional, tag = "2")]
    pub data_type: Option<i32>,
    /// The tensor's name (how nodes refer to it).
    #[prost(string, optional, tag = "8")]
    pub name: Option<String>,
    /// The elements, little-endian, row-major.
    #[prost(bytes = "vec", optional, tag = "9")]
    pub raw_data: Option<Vec<u8>>,
}

/// `ValueInfoProto`: a named, typed value (a graph input or output).
#[derive(Clone, PartialEq, prost::Message)]
pub struct ValueInfoProto {
    /// The value's name.
    #[prost(string, optional, tag = "1")]
    pub name: Option<String>,
    /// Its type.
    #[prost(message, optional, tag = "2")]
    pub r#type: Option<TypeProto>,
    /// Free text.
    #[prost(string, optional, tag = "3")]
    pub doc_string: Option<String>,
}

/// `TypeProto`; only its `tensor_type` member (field 1 of the `value` oneof) is declared.
#[derive(Clone, PartialEq, prost::Message)]
pub struct TypeProto {
    /// A dense tensor type.
    #[prost(message, optional, tag = "1")]
    pub tensor_type: Option<TypeProtoTensor>,
}

/// `TypeProto.Tensor`: an element type and a shape.
#[derive(Clone, PartialEq, prost::Message)]
pub struct TypeProtoTensor {
    /// The element type ([`FLOAT`], ...).
    #[prost(int32, optional, tag = "1")]
    pub elem_type: Option<i32>,
    /// The shape; dimensions may be symbolic.
    #[prost(message, optional, tag = "2")]
    pub shape: Option<TensorShapeProto>,
}

/// `TensorShapeProto`: a list of dimensions.
#[derive(Clone, PartialEq, prost::Message)]
pub struct TensorShapeProto {
    /// The dimensions, outermost first.
    #[prost(message, repeated, tag = "1")]
    pub dim: Vec<Dimension>,
}

/// `TensorShapeProto.Dimension`: a fixed size or a symbolic name.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Dimension {
    /// The `value` oneof.
    #[prost(oneof = "DimensionValue", tags = "1, 2")]
    pub value: Option<DimensionValue>,
}

/// The `value` oneof of [`Dimension`].
#[derive(Clone, PartialEq, prost::Oneof)]
pub enum DimensionValue {
    /// A fixed size (`dim_value`).
    #[prost(int64, tag = "1")]
    DimValue(i64),
    /// A symbolic size (`dim_param`), e.g. `batch`.
    #[prost(string, tag = "2")]
    DimParam(String),
}

/// An attribute with a single integer.
pub fn attr_int(name: &str, value: i64) -> AttributeProto {
    AttributeProto {
        name: Some(name.into()),
        r#type: Some(attribute_type::INT),
        i: Some(value),
        ..Default::default()
    }
}

/// An attribute with a list of integers.
pub fn attr_ints(name: &str, values: &[i64]) -> AttributeProto {
    AttributeProto {
        name: Some(name.into()),
        r#type: Some(attribute_type::INTS),
        ints: values.to_vec(),
        ..Default::default()
    }
}

/// An attribute with a single float.
pub fn attr_float(name: &str, value: f32) -> AttributeProto {
    AttributeProto {
        name: Some(name.into()),
        r#type: Some(attribute_type::FLOAT),
        f: Some(value),
        ..Default::default()
    }
}

/// An attribute with a string.
pub fn attr_string(name: &str, value: &str) -> AttributeProto {
    AttributeProto {
        name: Some(name.into()),
        r#type: Some(attribute_type::STRING),
        s: Some(value.as_bytes().to_vec()),
        ..Default::default()
    }
}

/// A node of the default domain.
pub fn node(
    op_type: &str,
    name: &str,
    inputs: &[&str],
    outputs: &[&str],
    attributes: Vec<AttributeProto>,
) -> NodeProto {
    NodeProto {
        input: inputs.iter().map(|s| s.to_string()).collect(),
        output: outputs.iter().map(|s| s.to_string()).collect(),
        name: Some(name.into()),
        op_type: Some(op_type.into()),
        attribute: attributes,
        ..Default::default()
    }
}

/// A float32 initializer with its data as little-endian `raw_data`.
pub fn initializer_f32(name: &str, dims: &[usize], data: &[f32]) -> TensorProto {
    let mut raw = Vec::with_capacity(data.len() * 4);
    for x in data {
        raw.extend_from_slice(&x.to_le_bytes());
    }
    TensorProto {
        dims: dims.iter().map(|&d| d as i64).collect(),
        data_type: Some(FLOAT),
        name: Some(name.into()),
        raw_data: Some(raw),
    }
}

/// An int64 initializer with its data as little-endian `raw_data`.
pub fn initializer_i64(name: &str, dims: &[usize], data: &[i64]) -> TensorProto {
    TensorProto {
        dims: dims.iter().map(|&d| d as i64).collect(),
        data_type: Some(INT64),
        name: Some(name.into()),
        raw_data: Some(data.iter().flat_map(|x| x.to_le_bytes()).collect()),
    }
}

/// A graph input or output: a float32 tensor whose dimensions are fixed (`Ok`) or named (`Err`).
pub fn tensor_value(
    name: &str,
    elem_type: i32,
    dims: &[std::result::Result<i64, &str>],
) -> ValueInfoProto {
    ValueInfoProto {
        name: Some(name.into()),
        r#type: Some(TypeProto {
            tensor_type: Some(TypeProtoTensor {
                elem_type: Some(elem_type),
                shape: Some(TensorShapeProto {
                    dim: dims
                        .iter()
                        .map(|d| Dimension {
                            value: Some(match d {
                                Ok(v) => DimensionValue::DimValue(*v),
                                Err(p) => DimensionValue::DimParam(p.to_string()),
                            }),
                        })
                        .collect(),
                }),
            }),
        }),
        doc_string: None,
    }
}

/// A model of one graph in the default domain at the project's opset and IR version.
pub fn model(
    graph: GraphProto,
    producer: &str,
    metadata_props: Vec<StringStringEntryProto>,
) -> ModelProto {
    ModelProto {
        ir_version: Some(IR_VERSION),
        opset_import: vec![OperatorSetIdProto {
            domain: Some(String::new()),
            version: Some(OPSET),
        }],
        producer_name: Some(producer.into()),
        producer_version: Some(env!("CARGO_PKG_VERSION").into()),
        model_version: Some(1),
        graph: Some(graph),
        metadata_props,
        ..Default::default()
    }
}

/// A metadata entry.
pub fn metadata(key: &str, value: &str) -> StringStringEntryProto {
    StringStringEntryProto {
        key: Some(key.into()),
        value: Some(value.into()),
    }
}

/// Encodes `model` onto `out` without building the whole encoding in memory: the graph's
/// initializers are written one at a time after the rest of the graph (protobuf allows fields in
/// any order, and repeated fields keep their relative order). Returns the bytes written; the
/// result decodes to `model` exactly.
pub fn write_model(mut model: ModelProto, out: &mut impl Write) -> std::io::Result<u64> {
    use prost::Message;
    let mut written = 0u64;
    let graph = model.graph.take();
    let head = model.encode_to_vec();
    write_counted(out, &head, &mut written)?;
    if let Some(mut graph) = graph {
        let initializers = std::mem::take(&mut graph.initializer);
        let body_len = graph.encoded_len()
            + initializers
                .iter()
                .map(|t| {
                    let len = t.encoded_len();
                    1 + prost::length_delimiter_len(len) + len
                })
                .sum::<usize>();
        let mut buf = Vec::with_capacity(16);
        buf.push((7 << 3) | 2); // ModelProto.graph, length-delimited
        prost::encode_length_delimiter(body_len, &mut buf).map_err(std::io::Error::other)?;
        write_counted(out, &buf, &mut written)?;
        write_counted(out, &graph.encode_to_vec(), &mut written)?;
        let mut buf = Vec::new();
        for t in initializers {
            buf.clear();
            buf.push((5 << 3) | 2); // GraphProto.initializer, length-delimited
            t.encode_length_delimited(&mut buf)
                .map_err(std::io::Error::other)?;
            drop(t);
            write_counted(out, &buf, &mut written)?;
        }
    }
    out.flush()?;
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;
    use prost::Message;

    #[test]
    fn streaming_encoding_decodes_to_the_same_model() {
        let graph = GraphProto {
            node: vec![node("Relu", "r", &["x"], &["y"], vec![attr_int("zero", 0)])],
            name: Some("g".into()),
            initializer: vec![
                initializer_f32("w0", &[2], &[1.0, -2.0]),
                initializer_f32("w1", &[1, 1], &[0.5]),
            ],
            input: vec![tensor_value("x", FLOAT, &[Err("batch"), Ok(3)])],
            output: vec![tensor_value("y", FLOAT, &[Err("batch"), Ok(3)])],
            ..Default::default()
        };
        let model = model(graph, "v2ce", vec![metadata("k", "v")]);
        let mut out = Vec::new();
        let n = write_model(model.clone(), &mut out).unwrap();
        assert_eq!(n as usize, out.len());
        assert_eq!(out.len(), model.encoded_len());
        let back = ModelProto::decode(out.as_slice()).unwrap();
        assert_eq!(back, model);
        // A zero-valued attribute is still present (proto2 presence).
        assert_eq!(back.graph.unwrap().node[0].attribute[0].i, Some(0));
    }

    #[test]
    fn field_numbers_match_onnx_proto() {
        // Hand-encoded bytes for ModelProto{ir_version: 8, graph: {name: "g"}} per onnx.proto:
        // field 1 varint 8; field 7 (graph) length-delimited holding field 2 (name) "g".
        let model = ModelProto {
            ir_version: Some(8),
            graph: Some(GraphProto {
                name: Some("g".into()),
                ..Default::default()
            }),
            ..Default::default()
        };
        assert_eq!(model.encode_to_vec(), vec![0x08, 8, 0x3a, 3, 0x12, 1, b'g']);
        // TensorProto: dims (1) unpacked, data_type (2), name (8), raw_data (9).
        let t = initializer_f32("w", &[1], &[0.0]);
        assert_eq!(
            t.encode_to_vec(),
            vec![0x08, 1, 0x10, 1, 0x42, 1, b'w', 0x4a, 4, 0, 0, 0, 0]
        );
        // A symbolic dimension is dim_param (2), a fixed one dim_value (1).
        let d = Dimension {
            value: Some(DimensionValue::DimParam("b".into())),
        };
        assert_eq!(d.encode_to_vec(), vec![0x12, 1, b'b']);
        // AttributeProto: name (1), i (3), type (20).
        let a = attr_int("n", 2);
        assert_eq!(
            a.encode_to_vec(),
            vec![0x0a, 1, b'n', 0x18, 2, 0xa0, 0x01, 2]
        );
    }
}
