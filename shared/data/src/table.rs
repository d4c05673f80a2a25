//! Parquet in and out through arrow arrays: the column types LeRobot uses (fixed-size float lists,
//! nested double lists for stats, string lists for tasks) and tolerant column readers for the
//! variants older datasets carry (list vs fixed-size list, float64 vs float32, int32 vs int64).

use std::path::{Path, PathBuf};
#[cfg(feature = "io")]
use std::sync::Arc;

use arrow_array::cast::AsArray;
use arrow_array::types::{Float32Type, Float64Type, Int32Type, Int64Type};
use arrow_array::{Array, ArrayRef, RecordBatch};
#[cfg(feature = "io")]
use arrow_array::{FixedSizeListArray, Float32Array, Float64Array, Int64Array, ListArray, StringArray};
use arrow_schema::DataType;
#[cfg(feature = "io")]
use arrow_schema::{Field, Schema};
#[cfg(feature = "io")]
use parquet::arrow::ArrowWriter;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
#[cfg(feature = "io")]
use parquet::basic::Compression;
#[cfg(feature = "io")]
use parquet::file::properties::WriterProperties;

use crate::error::{DataError, Result};
use crate::files::DatasetFiles;

/// pyarrow names list children "element"; matching it keeps our schemas identical to LeRobot's.
#[cfg(feature = "io")]
const LIST_ITEM: &str = "element";

#[cfg(feature = "io")]
pub fn fixed_size_f32_list(flat: Vec<f32>, dim: usize) -> ArrayRef {
    let item = Arc::new(Field::new(LIST_ITEM, DataType::Float32, true));
    Arc::new(FixedSizeListArray::new(item, dim as i32, Arc::new(Float32Array::from(flat)), None))
}

#[cfg(feature = "io")]
/// One list per row, nested to `shape` (e.g. `[6]` -> list<double>, `[3,1,1]` -> list<list<list<double>>>).
pub fn nested_f64_list(rows: &[&[f64]], shape: &[usize]) -> ArrayRef {
    let flat: Vec<f64> = rows.iter().flat_map(|r| r.iter().copied()).collect();
    let mut array: ArrayRef = Arc::new(Float64Array::from(flat));
    // Wrap from the innermost dimension outwards: level d holds rows * prod(shape[..d]) lists of shape[d].
    for depth in (0..shape.len()).rev() {
        let groups = rows.len() * shape[..depth].iter().product::<usize>();
        let field = Arc::new(Field::new(LIST_ITEM, array.data_type().clone(), true));
        array = Arc::new(ListArray::new(field, arrow_buffer_offsets(groups, shape[depth]), array, None));
    }
    array
}

#[cfg(feature = "io")]
fn arrow_buffer_offsets(groups: usize, len: usize) -> arrow_buffer::OffsetBuffer<i32> {
    arrow_buffer::OffsetBuffer::from_lengths(std::iter::repeat_n(len, groups))
}

#[cfg(feature = "io")]
/// One single-element list<int64> per row (how LeRobot stores per-episode `count`).
pub fn count_list(counts: &[i64]) -> ArrayRef {
    let field = Arc::new(Field::new(LIST_ITEM, DataType::Int64, true));
    Arc::new(ListArray::new(
        field,
        arrow_buffer_offsets(counts.len(), 1),
        Arc::new(Int64Array::from(counts.to_vec())),
        None,
    ))
}

#[cfg(feature = "io")]
pub fn string_lists(rows: &[Vec<String>]) -> ArrayRef {
    let flat: Vec<&str> = rows.iter().flat_map(|r| r.iter().map(String::as_str)).collect();
    let field = Arc::new(Field::new(LIST_ITEM, DataType::Utf8, true));
    let offsets = arrow_buffer::OffsetBuffer::from_lengths(rows.iter().map(Vec::len));
    Arc::new(ListArray::new(field, offsets, Arc::new(StringArray::from(flat)), None))
}

#[cfg(feature = "io")]
/// Writes `columns` as one snappy-compressed parquet file with `metadata` in the schema.
pub fn write_parquet(path: &Path, columns: Vec<(&str, ArrayRef)>, metadata: Vec<(&str, String)>) -> Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| DataError::io(dir, e))?;
    }
    let fields: Vec<Field> = columns.iter().map(|(n, a)| Field::new(*n, a.data_type().clone(), true)).collect();
    let schema = Arc::new(Schema::new(fields).with_metadata(
        metadata.into_iter().map(|(k, v)| (k.to_string(), v)).collect::<std::collections::HashMap<_, _>>(),
    ));
    let batch = RecordBatch::try_new(schema.clone(), columns.into_iter().map(|(_, a)| a).collect())
        .map_err(|e| DataError::parquet(path, e))?;
    let file = std::fs::File::create(path).map_err(|e| DataError::io(path, e))?;
    let props = WriterProperties::builder().set_compression(Compression::SNAPPY).build();
    let mut writer = ArrowWriter::try_new(file, schema, Some(props)).map_err(|e| DataError::parquet(path, e))?;
    writer.write(&batch).map_err(|e| DataError::parquet(path, e))?;
    writer.close().map_err(|e| DataError::parquet(path, e))?;
    Ok(())
}

/// A parquet file read fully into arrow record batches.
pub struct Table {
    pub path: PathBuf,
    batches: Vec<RecordBatch>,
}

impl Table {
    /// Reads the parquet file `path` of `files` whole.
    pub fn read(files: &dyn DatasetFiles, path: &Path) -> Result<Self> {
        let shown = files.display_path(path);
        let bytes = bytes::Bytes::from(files.read(path)?);
        let reader = ParquetRecordBatchReaderBuilder::try_new(bytes)
            .and_then(|b| b.with_batch_size(64 * 1024).build())
            .map_err(|e| DataError::parquet(&shown, e))?;
        let batches = reader.collect::<std::result::Result<Vec<_>, _>>().map_err(|e| DataError::parquet(&shown, e))?;
        Ok(Table { path: shown, batches })
    }

    pub fn num_rows(&self) -> usize {
        self.batches.iter().map(RecordBatch::num_rows).sum()
    }

    /// The column names, in file order.
    pub fn column_names(&self) -> Vec<String> {
        self.batches.first().map(|b| b.schema().fields().iter().map(|f| f.name().clone()).collect()).unwrap_or_default()
    }

    /// A column of (possibly nested) lists of numbers as one flat f64 vector per row, e.g. LeRobot's per-episode
    /// `stats/<feature>/<stat>` columns.
    pub fn flat_f64_rows(&self, name: &str) -> Result<Vec<Vec<f64>>> {
        let mut out = Vec::with_capacity(self.num_rows());
        for col in self.columns(name)? {
            let list =
                col.as_list_opt::<i32>().ok_or_else(|| self.bad_type(name, col.data_type(), "a list of numbers"))?;
            for i in 0..list.len() {
                out.push(
                    flat_numbers(&list.value(i))
                        .ok_or_else(|| self.bad_type(name, col.data_type(), "a list of numbers"))?,
                );
            }
        }
        Ok(out)
    }

    fn columns(&self, name: &str) -> Result<Vec<&ArrayRef>> {
        self.batches
            .iter()
            .map(|b| b.column_by_name(name).ok_or_else(|| DataError::column(&self.path, name, "missing")))
            .collect()
    }

    pub fn i64_column(&self, name: &str) -> Result<Vec<i64>> {
        let mut out = Vec::with_capacity(self.num_rows());
        for col in self.columns(name)? {
            if let Some(a) = col.as_primitive_opt::<Int64Type>() {
                out.extend(a.iter().map(Option::unwrap_or_default));
            } else if let Some(a) = col.as_primitive_opt::<Int32Type>() {
                out.extend(a.iter().map(|v| i64::from(v.unwrap_or_default())));
            } else {
                return Err(self.bad_type(name, col.data_type(), "an integer"));
            }
        }
        Ok(out)
    }

    pub fn f64_column(&self, name: &str) -> Result<Vec<f64>> {
        let mut out = Vec::with_capacity(self.num_rows());
        for col in self.columns(name)? {
            if let Some(a) = col.as_primitive_opt::<Float64Type>() {
                out.extend(a.iter().map(Option::unwrap_or_default));
            } else if let Some(a) = col.as_primitive_opt::<Float32Type>() {
                out.extend(a.iter().map(|v| f64::from(v.unwrap_or_default())));
            } else {
                return Err(self.bad_type(name, col.data_type(), "a float"));
            }
        }
        Ok(out)
    }

    pub fn string_column(&self, name: &str) -> Result<Vec<String>> {
        let mut out = Vec::with_capacity(self.num_rows());
        for col in self.columns(name)? {
            let a = col.as_string_opt::<i32>().ok_or_else(|| self.bad_type(name, col.data_type(), "a string"))?;
            out.extend(a.iter().map(|v| v.unwrap_or_default().to_string()));
        }
        Ok(out)
    }

    pub fn string_list_column(&self, name: &str) -> Result<Vec<Vec<String>>> {
        let mut out = Vec::with_capacity(self.num_rows());
        for col in self.columns(name)? {
            let list =
                col.as_list_opt::<i32>().ok_or_else(|| self.bad_type(name, col.data_type(), "a list of strings"))?;
            for i in 0..list.len() {
                let values = list.value(i);
                let strings = values
                    .as_string_opt::<i32>()
                    .ok_or_else(|| self.bad_type(name, col.data_type(), "a list of strings"))?;
                out.push(strings.iter().map(|v| v.unwrap_or_default().to_string()).collect());
            }
        }
        Ok(out)
    }

    /// A vector column (fixed-size or variable list of float32/float64) as flat float32 rows of `dim`.
    pub fn f32_rows(&self, name: &str, dim: usize) -> Result<Vec<f32>> {
        let mut out = Vec::with_capacity(self.num_rows() * dim);
        for col in self.columns(name)? {
            let (values, lengths): (&ArrayRef, Vec<usize>) = if let Some(l) = col.as_fixed_size_list_opt() {
                (l.values(), vec![l.value_length() as usize; l.len()])
            } else if let Some(l) = col.as_list_opt::<i32>() {
                (l.values(), l.offsets().windows(2).map(|w| (w[1] - w[0]) as usize).collect())
            } else {
                return Err(self.bad_type(name, col.data_type(), "a list of floats"));
            };
            if let Some(bad) = lengths.iter().find(|&&l| l != dim) {
                return Err(DataError::column(
                    &self.path,
                    name,
                    format!("rows have {bad} values, the feature has {dim}"),
                ));
            }
            let start = if let Some(l) = col.as_fixed_size_list_opt() {
                l.offset() * dim
            } else {
                col.as_list::<i32>().offsets()[0] as usize
            };
            let count = lengths.len() * dim;
            if let Some(v) = values.as_primitive_opt::<Float32Type>() {
                out.extend_from_slice(&v.values()[start..start + count]);
            } else if let Some(v) = values.as_primitive_opt::<Float64Type>() {
                out.extend(v.values()[start..start + count].iter().map(|&x| x as f32));
            } else {
                return Err(self.bad_type(name, col.data_type(), "a list of floats"));
            }
        }
        Ok(out)
    }

    fn bad_type(&self, name: &str, found: &DataType, expected: &str) -> DataError {
        DataError::column(&self.path, name, format!("expected {expected}, found {found}"))
    }
}

/// Every number of a (nested) list array, in order; `None` for anything else.
fn flat_numbers(array: &ArrayRef) -> Option<Vec<f64>> {
    if let Some(list) = array.as_list_opt::<i32>() {
        let mut out = Vec::new();
        for i in 0..list.len() {
            out.extend(flat_numbers(&list.value(i))?);
        }
        Some(out)
    } else if let Some(a) = array.as_primitive_opt::<Float64Type>() {
        Some(a.iter().map(Option::unwrap_or_default).collect())
    } else if let Some(a) = array.as_primitive_opt::<Float32Type>() {
        Some(a.iter().map(|v| f64::from(v.unwrap_or_default())).collect())
    } else {
        array.as_primitive_opt::<Int64Type>().map(|a| a.iter().map(|v| v.unwrap_or_default() as f64).collect())
    }
}
