-- Atomic commit of one step: check every fence, then write everything and release the leases, or write nothing.
-- Needs records.lua and leases.lua before it.
-- KEYS[1]: the map's processed-frames HASH, KEYS[2]: bounds HASH, KEYS[3]: metadata HASH,
-- KEYS[4]: the processed-frames counter, KEYS[5]: the processed-frames sweep cursor,
-- KEYS[6]: the retired objects' metadata HASH, KEYS[7]: when they were retired (ZSET),
-- KEYS[8]: the map's change log (STREAM), KEYS[9]: the map's version (STRING: the log's last entry),
-- KEYS[10]: when the log began (STRING, set with its first entry: Redis's TIME, "seconds.microseconds").
-- ARGV[1]: the map prefix "arcloud:{map}" (object and cell keys are built from it: one hash tag, one slot).
-- ARGV[2]: JSON {frame, entry_id, now, retention_s, sweep, leases: [[key, token]...], held: [id...],
--          upserts: [{id, version, cells}...], deletes: [{id, version}...], misses: [{id, count}...],
--          gone: [{id, count}...], retired: [{id, version}...], history_s, history_max, new_cells, max_cells,
--          log_max}
--          (leases: lock and claim keys, of the map's hash tag; ids, versions and counts as decimal strings;
--          frame "" for none; entry_id: the queue entry the frame was delivered from, "" for none: refused
--          within retention_s of its being given up (give_up_frame.lua, "<prefix>:given-up:<entry_id>");
--          cells: "i:j:k i:j:k ..." the index cells of the object's bounds; upserts also carry missed and gone,
--          the object's counters, kept in its hash beside the voxels; now: Unix s; a
--          frame recorded more than retention_s ago counts as not recorded, and each commit sweeps about `sweep`
--          records for such ones; retired objects are deleted like deletes and their metadata kept in the
--          history, which keeps those retired within history_s, at most history_max; new_cells: how many index
--          cells the upserts add, max_cells: the most cells one commit may add and remove together, counted
--          before anything is written).
--          log_max: about how many entries the change log keeps (XADD MAXLEN ~).
-- ARGV[3]: the change's events (``codec.encode_events``), "" for none: appended to the change log as the entry
--          "<version>-0" (the map's version + 1) with fields at (now), frame, events, after every check and
--          before any write, so that a refused commit appends nothing and a failed append writes nothing.
-- ARGV[4..]: per upsert in order, three values: packed bounds, metadata JSON, encoded voxels.
-- Returns 1 (written, and then the leases released in the same step, their waiters woken: the caller sends no
-- release), 0 (the frame was recorded before: nothing written), -N (the commit would add and remove N > max_cells
-- index cells: nothing written), or an error "STALE ..." (a fence failed: nothing written). But for 1, the
-- leases stay held.
local frames_key, bounds_key, meta_key, count_key, sweep_key = KEYS[1], KEYS[2], KEYS[3], KEYS[4], KEYS[5]
local history_key, history_at_key, log_key, version_key, began_key = KEYS[6], KEYS[7], KEYS[8], KEYS[9], KEYS[10]
local prefix = ARGV[1]
local req = cjson.decode(ARGV[2])
local cutoff = tonumber(req.now) - tonumber(req.retention_s)

local function object_key(id)
  return prefix .. ':obj:' .. id
end

local function stale(message)
  return redis.error_reply('STALE ' .. prefix .. ': ' .. message .. '; nothing written')
end

-- A delivery of an entry given up (its frame counted failed) writes nothing, whatever else holds.
local given_up_at = req.entry_id ~= '' and redis.call('GET', prefix .. ':given-up:' .. req.entry_id)
if given_up_at and tonumber(given_up_at) >= cutoff then
  return redis.error_reply('GIVENUP ' .. prefix .. ': frame ' .. req.frame .. ' of queue entry ' .. req.entry_id
    .. ' was given up (dead-lettered); nothing written')
end
if req.frame ~= '' then
  local recorded_at = redis.call('HGET', frames_key, req.frame)
  if recorded_at and tonumber(recorded_at) >= cutoff then
    return 0
  end
end

for _, lease in ipairs(req.leases) do
  if redis.call('GET', lease[1]) ~= lease[2] then
    return stale('lease on ' .. lease[1] .. ' expired or was taken over')
  end
end
local held = {}
for _, id in ipairs(req.held) do
  held[id] = true
end
for _, u in ipairs(req.upserts) do
  local current = redis.call('HGET', object_key(u.id), 'version')
  if not current then
    if u.version ~= '1' then
      return stale('object ' .. u.id .. ' written at version ' .. u.version .. ' but it does not exist')
    end
  else
    if not held[u.id] then
      return stale('object ' .. u.id .. ' written without its lock')
    end
    if tonumber(current) ~= tonumber(u.version) - 1 then
      return stale('object ' .. u.id .. ' is at version ' .. current .. ', write expected ' .. (tonumber(u.version) - 1))
    end
  end
end
for _, counters in ipairs({req.misses, req.gone}) do
  for _, m in ipairs(counters) do
    if redis.call('EXISTS', object_key(m.id)) == 1 and not held[m.id] then
      return stale('object ' .. m.id .. ' counted as missed without its lock')
    end
  end
end
for _, deleted in ipairs({req.deletes, req.retired}) do
  for _, d in ipairs(deleted) do
    local current = redis.call('HGET', object_key(d.id), 'version')
    if current and (not held[d.id] or tonumber(current) ~= tonumber(d.version)) then
      return stale('object ' .. d.id .. ' deleted without its lock or at a stale version')
    end
  end
end
-- The index cells this commit touches: those it adds, and those of the objects it rewrites or deletes, which it
-- removes (counted in their stored list, before anything is written: Redis serves no one while a script runs).
local touched = tonumber(req.new_cells)
for _, written in ipairs({req.upserts, req.deletes, req.retired}) do
  for _, w in ipairs(written) do
    local cells = redis.call('HGET', object_key(w.id), 'cells')
    if cells then
      local _, n = string.gsub(cells, '%S+', '')
      touched = touched + n
    end
  end
end
if touched > tonumber(req.max_cells) then
  return -touched
end

if ARGV[3] ~= '' then
  if redis.call('EXISTS', began_key) == 0 then
    local now = redis.call('TIME')
    redis.call('SET', began_key, now[1] .. '.' .. string.format('%06d', tonumber(now[2])))
  end
  local version = tonumber(redis.call('GET', version_key) or '0') + 1
  redis.call('XADD', log_key, 'MAXLEN', '~', req.log_max, version .. '-0', 'at', req.now, 'frame', req.frame, 'events', ARGV[3])
  redis.call('SET', version_key, version)
end

local function unindex(id)
  local cells = redis.call('HGET', object_key(id), 'cells')
  if cells then
    for cell in string.gmatch(cells, '%S+') do
      redis.call('SREM', prefix .. ':cell:' .. cell, id)
    end
  end
  redis.call('HDEL', bounds_key, id)
  redis.call('HDEL', meta_key, id)
end

for _, r in ipairs(req.retired) do
  local meta = redis.call('HGET', meta_key, r.id)
  if meta then
    redis.call('HSET', history_key, r.id, meta)
    redis.call('ZADD', history_at_key, req.now, r.id)
  end
end
for _, deleted in ipairs({req.deletes, req.retired}) do
  for _, d in ipairs(deleted) do
    unindex(d.id)
    redis.call('DEL', object_key(d.id))
  end
end
local at = 4
for _, u in ipairs(req.upserts) do
  local key = object_key(u.id)
  unindex(u.id)
  redis.call('DEL', key)
  redis.call('HSET', key, 'version', u.version, 'cells', u.cells, 'voxels', ARGV[at + 2], 'missed', u.missed, 'gone', u.gone)
  redis.call('HSET', bounds_key, u.id, ARGV[at])
  redis.call('HSET', meta_key, u.id, ARGV[at + 1])
  for cell in string.gmatch(u.cells, '%S+') do
    redis.call('SADD', prefix .. ':cell:' .. cell, u.id)
  end
  at = at + 3
end
for field, counters in pairs({missed = req.misses, gone = req.gone}) do
  for _, m in ipairs(counters) do
    if redis.call('EXISTS', object_key(m.id)) == 1 then
      redis.call('HSET', object_key(m.id), field, m.count)
    end
  end
end
if req.frame ~= '' then
  redis.call('HSET', frames_key, req.frame, req.now)
  redis.call('INCR', count_key)
end
sweep(frames_key, sweep_key, cutoff, tonumber(req.sweep), tonumber)
-- The history: drop those retired more than history_s ago (a bounded number a commit), then the oldest
-- beyond history_max.
local history_cutoff = tonumber(req.now) - tonumber(req.history_s)
local expired = redis.call('ZRANGEBYSCORE', history_at_key, '-inf', '(' .. history_cutoff, 'LIMIT', 0, tonumber(req.sweep))
local excess = redis.call('ZCARD', history_at_key) - #expired - tonumber(req.history_max)
if excess > 0 then
  for _, id in ipairs(redis.call('ZRANGE', history_at_key, #expired, #expired + excess - 1)) do
    expired[#expired + 1] = id
  end
end
for _, id in ipairs(expired) do
  redis.call('HDEL', history_key, id)
  redis.call('ZREM', history_at_key, id)
end
for _, lease in ipairs(req.leases) do
  release_lease(lease[1], lease[2])
end
return 1
