//! PyTorch `torch.save` archives: a reader that returns the state dict, and a writer.
//!
//! The format (PyTorch 1.6 and later) is a zip archive with stored (uncompressed) entries under one
//! top folder of any name:
//!
//! * `<top>/data.pkl`: a pickle (protocol 2) of the saved object. Tensors appear as calls to
//!   `torch._utils._rebuild_tensor_v2(storage, offset, size, stride, requires_grad, hooks[, metadata])`
//!   whose storage is a *persistent id* `('storage', torch.FloatStorage, key, location, numel)`;
//! * `<top>/data/<key>`: the raw little-endian bytes of each storage;
//! * `<top>/byteorder` (`little`) and `<top>/version`.
//!
//! The pickle is read by a small stack machine that understands the opcodes pickle writes for plain
//! data and **executes nothing**: a handful of known callables (`OrderedDict`, the tensor rebuild
//! functions, `_codecs.encode`) are interpreted, and any other global becomes an opaque object, so a
//! Lightning checkpoint's optimizer states and hyper-parameters are walked past. Storage bytes are
//! read lazily, only for the tensors asked for, and every size is checked against the real entry
//! lengths: a truncated or foreign file gives an error naming the file, never a panic or a huge
//! allocation.
//!
//! The parts, a file each:
//!
//! * `archive`: the reader, [`TorchArchive`] (open, find the state dict, read a tensor on demand)
//!   and [`read_state_dict`];
//! * `pickle`: the stack machine, its opcodes handled by family;
//! * `value`: the values the machine builds;
//! * `callables`: the few callables it interprets (tensor rebuilds, persistent storages, ...);
//! * `storage`: storage element types ([`StorageType`]) and the decoding of storage bytes;
//! * `writer`: [`write_state_dict`] and the pickle it writes.

mod archive;
mod callables;
mod pickle;
mod storage;
mod value;
mod writer;

pub use archive::{read_state_dict, TensorEntry, TorchArchive};
pub use storage::StorageType;
pub use writer::write_state_dict;
