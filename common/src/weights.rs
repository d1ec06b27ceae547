//! Named f32 tensors <-> safetensors bytes: the one format for weights on the wire and in
//! checkpoints (policy, critics, optimiser state).

use std::collections::{BTreeMap, HashMap};

use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use tch::{Device, Kind, Tensor};

#[derive(Debug, thiserror::Error)]
pub enum WeightsError {
    #[error("not a valid safetensors blob: {0}")]
    Format(String),
    #[error("tensor {name:?} has dtype {dtype}, only F32 is supported")]
    Dtype { name: String, dtype: String },
    #[error("tensor {0:?} is missing")]
    Missing(String),
    #[error("tensor {name:?} has shape {got:?}, expected {expected:?}")]
    Shape {
        name: String,
        got: Vec<i64>,
        expected: Vec<i64>,
    },
    #[error("tensor {name:?} holds a NaN or infinite value")]
    NonFinite { name: String },
    #[error("metadata {key:?} is missing or invalid")]
    Metadata { key: String },
    #[error("the checkpoint does not fit this run's configuration: {0}")]
    Mismatch(String),
    #[error("torch: {0}")]
    Torch(#[from] tch::TchError),
}

/// Safetensors metadata key holding our metadata as one JSON object. safetensors writes its
/// metadata map in hash order; one key keeps the bytes identical for identical inputs.
const METADATA_KEY: &str = "junction";

/// Encodes tensors (any device; stored as CPU f32, sorted by name) plus string metadata.
pub fn encode(
    tensors: &[(String, &Tensor)],
    metadata: BTreeMap<String, String>,
) -> Result<Vec<u8>, WeightsError> {
    let mut host: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::with_capacity(tensors.len());
    for (name, tensor) in tensors {
        let cpu = tensor
            .detach()
            .to_device(Device::Cpu)
            .to_kind(Kind::Float)
            .contiguous();
        let shape: Vec<usize> = cpu.size().iter().map(|&d| d as usize).collect();
        let values = Vec::<f32>::try_from(cpu.flatten(0, -1))?;
        let bytes = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        host.push((name.clone(), shape, bytes));
    }
    host.sort_by(|a, b| a.0.cmp(&b.0));
    let views = host
        .iter()
        .map(|(name, shape, bytes)| {
            TensorView::new(Dtype::F32, shape.clone(), bytes)
                .map(|view| (name.clone(), view))
                .map_err(|e| WeightsError::Format(format!("{e:?}")))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let metadata_json =
        serde_json::to_string(&metadata).map_err(|e| WeightsError::Format(e.to_string()))?;
    let header = HashMap::from([(METADATA_KEY.to_string(), metadata_json)]);
    safetensors::tensor::serialize(views, &Some(header))
        .map_err(|e| WeightsError::Format(format!("{e:?}")))
}

/// Decoded blob: CPU tensors by name, and the metadata.
pub struct Decoded {
    pub tensors: HashMap<String, Tensor>,
    pub metadata: BTreeMap<String, String>,
}

/// The metadata of a blob, read from its header alone (no tensor is decoded).
pub fn metadata(bytes: &[u8]) -> Result<BTreeMap<String, String>, WeightsError> {
    let (_, header) =
        SafeTensors::read_metadata(bytes).map_err(|e| WeightsError::Format(format!("{e:?}")))?;
    match header.metadata().as_ref().and_then(|m| m.get(METADATA_KEY)) {
        Some(json) => serde_json::from_str(json).map_err(|_| WeightsError::Metadata {
            key: METADATA_KEY.to_string(),
        }),
        None => Ok(BTreeMap::new()),
    }
}

impl WeightsError {
    /// Whether the blob is sound but was written for another configuration (a tensor missing
    /// or of another shape, a learned quantity outside this run's bounds), as opposed to
    /// damaged bytes: restoring it under the configuration it came from would work.
    pub fn is_configuration_mismatch(&self) -> bool {
        matches!(
            self,
            WeightsError::Missing(_) | WeightsError::Shape { .. } | WeightsError::Mismatch(_)
        )
    }
}

impl Decoded {
    pub fn decode(bytes: &[u8]) -> Result<Self, WeightsError> {
        let st =
            SafeTensors::deserialize(bytes).map_err(|e| WeightsError::Format(format!("{e:?}")))?;
        let metadata = metadata(bytes)?;
        let mut tensors = HashMap::new();
        for (name, view) in st.tensors() {
            if view.dtype() != Dtype::F32 {
                return Err(WeightsError::Dtype {
                    name,
                    dtype: format!("{:?}", view.dtype()),
                });
            }
            let values: Vec<f32> = view
                .data()
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            if values.iter().any(|v| !v.is_finite()) {
                return Err(WeightsError::NonFinite { name });
            }
            let shape = view
                .shape()
                .iter()
                .map(|&d| i64::try_from(d))
                .collect::<Result<Vec<i64>, _>>()
                .map_err(|_| WeightsError::Format(format!("tensor {name:?} has a huge shape")))?;
            let tensor = Tensor::from_slice(&values).f_reshape(&shape)?;
            tensors.insert(name, tensor);
        }
        Ok(Decoded { tensors, metadata })
    }

    /// Values held over all tensors (what a blob can fill, whatever its metadata claims).
    pub fn total_values(&self) -> i64 {
        self.tensors
            .values()
            .map(Tensor::numel)
            .map(|n| n as i64)
            .sum()
    }

    /// The tensor `name`, checked against `expected` shape.
    pub fn take(&mut self, name: &str, expected: &[i64]) -> Result<Tensor, WeightsError> {
        let t = self
            .tensors
            .remove(name)
            .ok_or_else(|| WeightsError::Missing(name.to_string()))?;
        if t.size() != expected {
            return Err(WeightsError::Shape {
                name: name.to_string(),
                got: t.size(),
                expected: expected.to_vec(),
            });
        }
        Ok(t)
    }

    pub fn meta<T: std::str::FromStr>(&self, key: &str) -> Result<T, WeightsError> {
        self.metadata
            .get(key)
            .and_then(|v| v.parse().ok())
            .ok_or_else(|| WeightsError::Metadata {
                key: key.to_string(),
            })
    }
}

/// Copies every variable of `vs` from `decoded` (shapes checked), without tracking gradients.
pub fn load_var_store(vs: &tch::nn::VarStore, decoded: &mut Decoded) -> Result<(), WeightsError> {
    let mut variables: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    variables.sort_by(|a, b| a.0.cmp(&b.0));
    // Check everything before changing anything, so a bad blob leaves the store intact.
    let mut sources = Vec::with_capacity(variables.len());
    for (name, var) in &variables {
        sources.push(decoded.take(name, &var.size())?);
    }
    tch::no_grad(|| {
        for ((_, mut var), src) in variables.into_iter().zip(sources) {
            var.copy_(&src);
        }
    });
    Ok(())
}

/// Every variable of `vs` as (name, tensor), for [`encode`].
pub fn var_store_tensors(vs: &tch::nn::VarStore) -> Vec<(String, Tensor)> {
    let mut variables: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    variables.sort_by(|a, b| a.0.cmp(&b.0));
    variables
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_preserves_values_and_metadata() {
        let a = Tensor::from_slice(&[1.0f32, -2.5, 3.25, 0.0, 7.0, 8.0]).reshape([2, 3]);
        let b = Tensor::from_slice(&[0.5f32]);
        let meta = BTreeMap::from([("version".to_string(), "12".to_string())]);
        let bytes = encode(&[("a".into(), &a), ("b".into(), &b)], meta).unwrap();
        let mut d = Decoded::decode(&bytes).unwrap();
        assert_eq!(d.meta::<u64>("version").unwrap(), 12);
        assert!(d.take("a", &[3, 2]).is_err(), "shape is checked");
        let mut d = Decoded::decode(&bytes).unwrap();
        let a2 = d.take("a", &[2, 3]).unwrap();
        assert_eq!(
            Vec::<f32>::try_from(a2.flatten(0, -1)).unwrap(),
            vec![1.0, -2.5, 3.25, 0.0, 7.0, 8.0]
        );
        assert!(matches!(
            d.take("missing", &[1]),
            Err(WeightsError::Missing(_))
        ));
        let again = encode(&[("a".into(), &a), ("b".into(), &b)], d.metadata.clone()).unwrap();
        assert_eq!(again, bytes, "identical inputs give identical bytes");
    }

    #[test]
    fn garbage_and_nan_are_errors_not_panics() {
        assert!(Decoded::decode(b"not safetensors").is_err());
        assert!(Decoded::decode(&[]).is_err());
        let nan = Tensor::from_slice(&[f32::NAN]);
        let bytes = encode(&[("x".into(), &nan)], BTreeMap::new()).unwrap();
        assert!(matches!(
            Decoded::decode(&bytes),
            Err(WeightsError::NonFinite { .. })
        ));
        // Truncated blobs are refused.
        let ok = encode(
            &[("x".into(), &Tensor::from_slice(&[1.0f32, 2.0]))],
            BTreeMap::new(),
        )
        .unwrap();
        assert!(Decoded::decode(&ok[..ok.len() - 3]).is_err());
    }

    /// A safetensors header written by hand: `json` then `data`.
    fn raw_blob(json: &str, data: &[u8]) -> Vec<u8> {
        let mut bytes = (json.len() as u64).to_le_bytes().to_vec();
        bytes.extend_from_slice(json.as_bytes());
        bytes.extend_from_slice(data);
        bytes
    }

    #[test]
    fn hostile_headers_are_errors_not_panics() {
        // A zero-sized tensor with a dimension beyond i64: the product is 0, so the data
        // length checks out, but no tensor of that shape can exist.
        let huge = raw_blob(
            r#"{"x":{"dtype":"F32","shape":[0,18446744073709551615],"data_offsets":[0,0]}}"#,
            &[],
        );
        assert!(Decoded::decode(&huge).is_err());
        // Data offsets past the end, other dtypes, a header longer than the blob.
        let past = raw_blob(
            r#"{"x":{"dtype":"F32","shape":[2],"data_offsets":[0,8]}}"#,
            &[0; 4],
        );
        assert!(Decoded::decode(&past).is_err());
        let ints = raw_blob(
            r#"{"x":{"dtype":"I32","shape":[1],"data_offsets":[0,4]}}"#,
            &[0; 4],
        );
        assert!(matches!(
            Decoded::decode(&ints),
            Err(WeightsError::Dtype { .. })
        ));
        let mut long_header = raw_blob("{}", &[]);
        long_header[..8].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(Decoded::decode(&long_header).is_err());
        // Metadata that is not our JSON object.
        let bad_meta = raw_blob(r#"{"__metadata__":{"junction":"[1,2"}}"#, &[]);
        assert!(matches!(
            Decoded::decode(&bad_meta),
            Err(WeightsError::Metadata { .. })
        ));
    }
}
