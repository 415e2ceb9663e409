// A small msgpack codec limited to the types EgoPose protocol v1 uses (PROTOCOL.md §2): nil, bool, integers,
// float32/float64, str, bin, arrays and maps with string keys. No extension types, no timestamps.
//
// Values are plain .NET objects:
//   nil -> null, bool -> bool, int -> long (ulong above long.MaxValue), float32 -> float, float64 -> double,
//   str -> string, bin -> byte[], array -> List<object>, map -> MsgMap (keeps the wire's key order).
// The writer picks the shortest encoding of each integer, string, bin, array and map header, which is what
// msgpack-python (the server) does, so a decoded message re-encodes to the same bytes.
//
// Pure C#: no UnityEngine, no I/O. Compiled and tested outside Unity with Mono (tests/clients/test_unity_core.py).
using System;
using System.Collections;
using System.Collections.Generic;
using System.Text;

namespace EgoPose.Protocol
{
    /// <summary>Bytes that are not one msgpack value of the protocol's types (truncated, ext type, ...).</summary>
    public sealed class MsgPackException : Exception
    {
        public MsgPackException(string message) : base(message) { }
    }

    /// <summary>A msgpack map with string keys that keeps its entries in insertion (wire) order.</summary>
    public sealed class MsgMap : IEnumerable<KeyValuePair<string, object>>
    {
        readonly List<KeyValuePair<string, object>> entries = new List<KeyValuePair<string, object>>();

        public int Count { get { return entries.Count; } }

        /// <summary>Appends an entry (a key already present is replaced in place).</summary>
        public MsgMap Add(string key, object value)
        {
            for (int i = 0; i < entries.Count; i++)
            {
                if (entries[i].Key == key)
                {
                    entries[i] = new KeyValuePair<string, object>(key, value);
                    return this;
                }
            }
            entries.Add(new KeyValuePair<string, object>(key, value));
            return this;
        }

        public bool TryGetValue(string key, out object value)
        {
            foreach (var entry in entries)
            {
                if (entry.Key == key)
                {
                    value = entry.Value;
                    return true;
                }
            }
            value = null;
            return false;
        }

        /// <summary>The value under <paramref name="key"/>, or null when absent (absent and nil are alike, §2).</summary>
        public object Get(string key)
        {
            object value;
            return TryGetValue(key, out value) ? value : null;
        }

        public IEnumerator<KeyValuePair<string, object>> GetEnumerator() { return entries.GetEnumerator(); }

        IEnumerator IEnumerable.GetEnumerator() { return entries.GetEnumerator(); }
    }

    /// <summary>Encode and decode whole messages.</summary>
    public static class MsgPack
    {
        public static byte[] Encode(object value)
        {
            var writer = new MsgPackWriter();
            writer.WriteValue(value);
            return writer.ToArray();
        }

        /// <summary>One msgpack value filling all of <paramref name="data"/>; trailing bytes are an error.</summary>
        public static object Decode(byte[] data)
        {
            return Decode(data, 0, data.Length);
        }

        public static object Decode(byte[] data, int offset, int count)
        {
            var reader = new MsgPackReader(data, offset, count);
            object value = reader.ReadValue();
            if (reader.Remaining != 0)
                throw new MsgPackException(reader.Remaining + " trailing bytes after the value");
            return value;
        }
    }

    /// <summary>Appends msgpack values to a growing buffer.</summary>
    public sealed class MsgPackWriter
    {
        byte[] buffer = new byte[256];
        int length;

        public int Length { get { return length; } }

        public byte[] ToArray()
        {
            var result = new byte[length];
            Buffer.BlockCopy(buffer, 0, result, 0, length);
            return result;
        }

        public void WriteValue(object value)
        {
            if (value == null) { WriteNil(); return; }
            if (value is bool) { WriteBool((bool)value); return; }
            if (value is float) { WriteFloat32((float)value); return; }
            if (value is double) { WriteFloat64((double)value); return; }
            if (value is string) { WriteString((string)value); return; }
            if (value is byte[]) { WriteBin((byte[])value); return; }
            if (value is ulong) { WriteUInt((ulong)value); return; }
            if (value is long || value is int || value is short || value is sbyte || value is uint
                || value is ushort || value is byte)
            {
                WriteInt(Convert.ToInt64(value));
                return;
            }
            var map = value as MsgMap;
            if (map != null)
            {
                WriteMapHeader(map.Count);
                foreach (var entry in map)
                {
                    WriteString(entry.Key);
                    WriteValue(entry.Value);
                }
                return;
            }
            var floats = value as float[];
            if (floats != null)
            {
                WriteArrayHeader(floats.Length);
                foreach (float f in floats) WriteFloat32(f);
                return;
            }
            var list = value as IList;
            if (list != null)
            {
                WriteArrayHeader(list.Count);
                foreach (object item in list) WriteValue(item);
                return;
            }
            throw new ArgumentException("msgpack cannot encode a " + value.GetType().Name);
        }

        public void WriteNil() { Put(0xc0); }

        public void WriteBool(bool value) { Put(value ? (byte)0xc3 : (byte)0xc2); }

        public void WriteInt(long value)
        {
            if (value >= 0) { WriteUInt((ulong)value); return; }
            if (value >= -32) { Put((byte)(sbyte)value); return; }
            if (value >= sbyte.MinValue) { Put(0xd0); Put((byte)(sbyte)value); return; }
            if (value >= short.MinValue) { Put(0xd1); PutBigEndian((ulong)value, 2); return; }
            if (value >= int.MinValue) { Put(0xd2); PutBigEndian((ulong)value, 4); return; }
            Put(0xd3);
            PutBigEndian((ulong)value, 8);
        }

        public void WriteUInt(ulong value)
        {
            if (value < 128) { Put((byte)value); return; }
            if (value <= byte.MaxValue) { Put(0xcc); Put((byte)value); return; }
            if (value <= ushort.MaxValue) { Put(0xcd); PutBigEndian(value, 2); return; }
            if (value <= uint.MaxValue) { Put(0xce); PutBigEndian(value, 4); return; }
            Put(0xcf);
            PutBigEndian(value, 8);
        }

        public void WriteFloat32(float value)
        {
            Put(0xca);
            PutBigEndian((uint)BitConverter.ToInt32(BitConverter.GetBytes(value), 0), 4);
        }

        public void WriteFloat64(double value)
        {
            Put(0xcb);
            PutBigEndian((ulong)BitConverter.DoubleToInt64Bits(value), 8);
        }

        public void WriteString(string value)
        {
            byte[] utf8 = Encoding.UTF8.GetBytes(value);
            int n = utf8.Length;
            if (n < 32) Put((byte)(0xa0 | n));
            else if (n <= byte.MaxValue) { Put(0xd9); Put((byte)n); }
            else if (n <= ushort.MaxValue) { Put(0xda); PutBigEndian((ulong)n, 2); }
            else { Put(0xdb); PutBigEndian((ulong)n, 4); }
            PutBytes(utf8);
        }

        public void WriteBin(byte[] value)
        {
            int n = value.Length;
            if (n <= byte.MaxValue) { Put(0xc4); Put((byte)n); }
            else if (n <= ushort.MaxValue) { Put(0xc5); PutBigEndian((ulong)n, 2); }
            else { Put(0xc6); PutBigEndian((ulong)n, 4); }
            PutBytes(value);
        }

        public void WriteArrayHeader(int count)
        {
            if (count < 16) Put((byte)(0x90 | count));
            else if (count <= ushort.MaxValue) { Put(0xdc); PutBigEndian((ulong)count, 2); }
            else { Put(0xdd); PutBigEndian((ulong)count, 4); }
        }

        public void WriteMapHeader(int count)
        {
            if (count < 16) Put((byte)(0x80 | count));
            else if (count <= ushort.MaxValue) { Put(0xde); PutBigEndian((ulong)count, 2); }
            else { Put(0xdf); PutBigEndian((ulong)count, 4); }
        }

        void Reserve(int extra)
        {
            if (length + extra <= buffer.Length) return;
            int size = buffer.Length;
            while (size < length + extra) size *= 2;
            Array.Resize(ref buffer, size);
        }

        void Put(byte b)
        {
            Reserve(1);
            buffer[length++] = b;
        }

        void PutBytes(byte[] bytes)
        {
            Reserve(bytes.Length);
            Buffer.BlockCopy(bytes, 0, buffer, length, bytes.Length);
            length += bytes.Length;
        }

        void PutBigEndian(ulong value, int byteCount)
        {
            Reserve(byteCount);
            for (int i = byteCount - 1; i >= 0; i--) buffer[length++] = (byte)(value >> (8 * i));
        }
    }

    /// <summary>Reads msgpack values from a byte range, refusing anything outside the protocol's types.</summary>
    public sealed class MsgPackReader
    {
        const int MaxDepth = 32; // v1 nests three deep; anything far beyond is hostile
        readonly byte[] data;
        readonly int end;
        int position;

        public MsgPackReader(byte[] data, int offset, int count)
        {
            if (offset < 0 || count < 0 || offset + count > data.Length)
                throw new ArgumentOutOfRangeException("count");
            this.data = data;
            position = offset;
            end = offset + count;
        }

        public int Remaining { get { return end - position; } }

        public object ReadValue() { return ReadValue(0); }

        object ReadValue(int depth)
        {
            if (depth > MaxDepth) throw new MsgPackException("nested deeper than " + MaxDepth);
            byte b = Take();
            if (b <= 0x7f) return (long)b;
            if (b >= 0xe0) return (long)(sbyte)b;
            if ((b & 0xf0) == 0x80) return ReadMap(b & 0x0f, depth);
            if ((b & 0xf0) == 0x90) return ReadArray(b & 0x0f, depth);
            if ((b & 0xe0) == 0xa0) return ReadString(b & 0x1f);
            switch (b)
            {
                case 0xc0: return null;
                case 0xc2: return false;
                case 0xc3: return true;
                case 0xc4: return ReadBin((int)ReadBigEndian(1));
                case 0xc5: return ReadBin((int)ReadBigEndian(2));
                case 0xc6: return ReadBin(Length(ReadBigEndian(4)));
                case 0xca: return BitConverter.ToSingle(BitConverter.GetBytes((uint)ReadBigEndian(4)), 0);
                case 0xcb: return BitConverter.Int64BitsToDouble((long)ReadBigEndian(8));
                case 0xcc: return (long)ReadBigEndian(1);
                case 0xcd: return (long)ReadBigEndian(2);
                case 0xce: return (long)ReadBigEndian(4);
                case 0xcf:
                {
                    ulong u = ReadBigEndian(8);
                    return u <= long.MaxValue ? (object)(long)u : u;
                }
                case 0xd0: return (long)(sbyte)ReadBigEndian(1);
                case 0xd1: return (long)(short)ReadBigEndian(2);
                case 0xd2: return (long)(int)ReadBigEndian(4);
                case 0xd3: return (long)ReadBigEndian(8);
                case 0xd9: return ReadString((int)ReadBigEndian(1));
                case 0xda: return ReadString((int)ReadBigEndian(2));
                case 0xdb: return ReadString(Length(ReadBigEndian(4)));
                case 0xdc: return ReadArray((int)ReadBigEndian(2), depth);
                case 0xdd: return ReadArray(Length(ReadBigEndian(4)), depth);
                case 0xde: return ReadMap((int)ReadBigEndian(2), depth);
                case 0xdf: return ReadMap(Length(ReadBigEndian(4)), depth);
            }
            if (b == 0xc1) throw new MsgPackException("byte 0xc1 is never used in msgpack");
            throw new MsgPackException(string.Format("type byte 0x{0:x2} (extension types are not allowed)", b));
        }

        int Length(ulong n)
        {
            // Every item takes at least one byte, so a count beyond what is left cannot be honest.
            if (n > (ulong)Remaining) throw new MsgPackException("length " + n + " runs past the end");
            return (int)n;
        }

        List<object> ReadArray(int count, int depth)
        {
            Length((ulong)count);
            var items = new List<object>(count);
            for (int i = 0; i < count; i++) items.Add(ReadValue(depth + 1));
            return items;
        }

        MsgMap ReadMap(int count, int depth)
        {
            Length((ulong)count);
            var map = new MsgMap();
            for (int i = 0; i < count; i++)
            {
                string key = ReadValue(depth + 1) as string;
                if (key == null) throw new MsgPackException("map keys must be strings");
                map.Add(key, ReadValue(depth + 1));
            }
            return map;
        }

        string ReadString(int n)
        {
            Length((ulong)n);
            try
            {
                string s = new UTF8Encoding(false, true).GetString(data, position, n);
                position += n;
                return s;
            }
            catch (ArgumentException)
            {
                throw new MsgPackException("a string is not valid UTF-8");
            }
        }

        byte[] ReadBin(int n)
        {
            Length((ulong)n);
            var bytes = new byte[n];
            Buffer.BlockCopy(data, position, bytes, 0, n);
            position += n;
            return bytes;
        }

        byte Take()
        {
            if (position >= end) throw new MsgPackException("truncated: the data ends inside a value");
            return data[position++];
        }

        ulong ReadBigEndian(int byteCount)
        {
            if (Remaining < byteCount) throw new MsgPackException("truncated: the data ends inside a value");
            ulong value = 0;
            for (int i = 0; i < byteCount; i++) value = (value << 8) | data[position++];
            return value;
        }
    }
}
