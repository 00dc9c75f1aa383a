-- Remove a map's objects, index, frames, id counter and history of retired objects atomically.
-- KEYS[1]: bounds HASH, KEYS[2]: processed-frames HASH, KEYS[3]: id counter, KEYS[4]: metadata HASH,
-- KEYS[5]: processed-frames counter, KEYS[6]: retired objects' HASH, KEYS[7]: their retirement times (ZSET).
-- ARGV[1]: the map prefix.
-- Returns the number of objects removed. (Leases expire by themselves; the caller sweeps them.)
local prefix = ARGV[1]
local ids = redis.call('HKEYS', KEYS[1])
for _, id in ipairs(ids) do
  local key = prefix .. ':obj:' .. id
  local cells = redis.call('HGET', key, 'cells')
  if cells then
    for cell in string.gmatch(cells, '%S+') do
      redis.call('DEL', prefix .. ':cell:' .. cell)
    end
  end
  redis.call('DEL', key)
end
redis.call('DEL', KEYS[1], KEYS[2], KEYS[3], KEYS[4], KEYS[5], KEYS[6], KEYS[7])
return #ids
