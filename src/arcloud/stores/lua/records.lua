-- Records of frames, shared by the scripts that write them (prepended to accept_frame.lua,
-- settle_frame.lua and commit.lua: the functions below are theirs).
-- A map's frame record (``ingest:status`` HASH value): "queued <entry id>", "processed <settled_at_s>" or
-- "failed <settled_at_s> <dead-letter id> <deliveries> <reason>"; a processed mark (``processed`` HASH
-- value): "<recorded_at_s>".

-- When the record's frame settled (Unix s); nil while it is queued; 0 for a record written before
-- records carried their time (expired at once).
local function settled_at(record)
  if string.sub(record, 1, 7) == 'queued ' then
    return nil
  end
  return tonumber(string.match(record, '^%a+ (%d[%d%.]*)')) or 0
end

-- Drop the HASH's records older than cutoff: HSCAN on from the cursor kept in cursor_key, about count
-- fields a call (a small HASH, encoded as a listpack, answers whole), so each call does bounded work and
-- every record is looked at once a sweep of the HASH. time_of(value): the record's time, nil to keep it.
local function sweep(hash_key, cursor_key, cutoff, count, time_of)
  local reply = redis.call('HSCAN', hash_key, redis.call('GET', cursor_key) or '0', 'COUNT', count)
  local fields = reply[2]
  for i = 1, #fields, 2 do
    local at = time_of(fields[i + 1])
    if at and at < cutoff then
      redis.call('HDEL', hash_key, fields[i])
    end
  end
  if reply[1] == '0' then
    redis.call('DEL', cursor_key)
  else
    redis.call('SET', cursor_key, reply[1])
  end
end

